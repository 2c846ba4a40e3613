"""The record as ROS 2 tools and Foxglove see it: one short `skinsafe run --record DIR --foxglove 0` with a poke,
a Foxglove WebSocket client connected while it runs; independent readers (rosbags with the ROS 2 Jazzy type
store, mcap-ros2-support) decode every message; the skin sits where the taxel map and the recorded /tf put it;
what Foxglove received equals the record."""
import json
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from skinsafe.core.bench.foxglove_client import watch
from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.runtime.foxglove_layout import layout
from skinsafe.core.runtime.recording import Recording
from skinsafe.core.runtime.ros2_msgs import typestore
from skinsafe.core.runtime.ros2_topics import TOPICS, Ros2Topics
from skinsafe.core.runtime.rosbag2 import record_file
from skinsafe.core.runtime.tick import Tick
from skinsafe.core.skin.taxel_map import load, save

pytestmark = [pytest.mark.xdist_group("ros2-record")]  # one worker runs the module's one run
LIVE = ["/tf", "/skinsafe/tactile", "/robot_description"]


@pytest.fixture(scope="module")
def ur5():
    robot = build_ur5()
    return robot, make_sample_design("ur5", pitch=0.02, robot=robot)  # 485 taxels


@pytest.fixture(scope="module")
def run(ur5, tmp_path_factory, realtime_turn):
    """The run's record folder, its map, and what a Foxglove client got while it ran (the real-time slot held while
    it runs; the tests' decoding runs beside the real-time tests)."""
    tmp = tmp_path_factory.mktemp("ros2")
    save(ur5[1], tmp / "skin.json")
    with realtime_turn():
        return _run(tmp)


def _run(tmp):
    proc = subprocess.Popen([sys.executable, "-m", "skinsafe.core.app.cli", "run", tmp / "skin.json", "--robot", "sim",
                             "--boards", "emulate", "--command", "hold", "--link-latency", "0.5", "--allow-link-latency",
                             "--tare-frames", "10", "--contact", "poke:at=0.3", "--seconds", "1.2",
                             "--record", tmp / "run", "--foxglove", "0"], stderr=subprocess.PIPE, text=True)
    live, err = {}, []
    for line in proc.stderr:
        err.append(line)
        if "Foxglove at ws://" in line:
            url = line.split(" at ")[1].split()[0]
            client = threading.Thread(target=lambda: live.update(watch(url, LIVE, seconds=60)))
            client.start()
            break
    err += proc.stderr.readlines()
    assert proc.wait(60) == 0, "".join(err)
    client.join()
    return tmp / "run", tmp / "skin.json", live


def rosbags_messages(folder: Path) -> dict:
    """topic -> decoded messages, by rosbags (ROS 2 Jazzy type store; the bag's own schemas for the rest)."""
    out = {}
    with AnyReader([folder], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        for con, _, raw in reader.messages():
            out.setdefault(con.topic, []).append(reader.deserialize(raw, con.msgtype))
        assert {c.topic: c.msgcount for c in reader.connections if c.msgcount} == {t: len(m) for t, m in out.items()}
    return out


def log_times(folder: Path, topic: str) -> np.ndarray:
    with AnyReader([folder]) as reader:
        return np.array([ns for _, ns, _ in reader.messages([c for c in reader.connections if c.topic == topic])])


def stamp(msg) -> float:
    s = msg.header.stamp if hasattr(msg, "header") else msg.transforms[0].header.stamp
    return s.sec + s.nanosec * 1e-9


def links(tf) -> dict:
    """child frame -> (parent frame, R, p) of a TFMessage."""
    out = {}
    for t in tf.transforms:
        r, v = t.transform.rotation, t.transform.translation
        R = np.zeros(9)
        mujoco.mju_quat2Mat(R, np.array([r.w, r.x, r.y, r.z]))
        out[t.child_frame_id] = (t.header.frame_id, R.reshape(3, 3), np.array([v.x, v.y, v.z]))
    return out


def world_poses(tf) -> dict:
    """frame -> (R, p) in `world`, composed along a TFMessage's parent links."""
    edges = links(tf)
    out = {"world": (np.eye(3), np.zeros(3))}

    def pose(frame):
        if frame not in out:
            parent, R, p = edges[frame]
            R0, p0 = pose(parent)
            out[frame] = (R0 @ R, R0 @ p + p0)
        return out[frame]

    for f in edges:
        pose(f)
    return out


def cloud(msg) -> np.ndarray:
    """A PointCloud2's float32 fields as (K, F)."""
    assert all(f.datatype == 7 and f.offset == 4 * i for i, f in enumerate(msg.fields))
    return np.frombuffer(bytes(msg.data), "<f4").reshape(msg.width, len(msg.fields))


def test_rosbags_decodes_every_message_of_every_topic(run):
    folder, skin, _ = run
    msgs = rosbags_messages(folder)
    assert set(TOPICS) <= set(msgs) and len(msgs["/tf"]) == len(msgs["/skinsafe/skin"]) >= 10  # 30 Hz of 1.2 s
    jazzy = get_typestore(Stores.ROS2_JAZZY)
    with AnyReader([folder]) as reader:  # the standard types as ROS 2 Jazzy defines them (hash of every field)
        for c in reader.connections:
            if c.msgtype in jazzy.fielddefs:
                assert c.digest == jazzy.hash_rihs01(c.msgtype), c.topic
        qos = {c.topic: c.ext.offered_qos_profiles[0].durability.name for c in reader.connections}
    assert qos["/robot_description"] == qos["/tf_static"] == "TRANSIENT_LOCAL" and qos["/tf"] == "VOLATILE"
    urdf = msgs["/robot_description"][0].data
    design = load(skin)
    assert urdf.count("<link name=\"taxel_") == design.n_taxels
    tactile = msgs["/skinsafe/tactile"]  # at 30 Hz: the newest of the float64 forces the layers saw, as float32
    assert len(tactile) == len(msgs["/tf"])
    forces = np.array([m.force for m in msgs["/skinsafe/forces"]])
    newest = np.searchsorted(log_times(folder, "/skinsafe/forces"), log_times(folder, "/skinsafe/tactile"), "right") - 1
    t = design.taxels
    names = {b.id: b.name for b in design.boards}
    for m, f in zip(tactile, forces[newest]):
        sensors = {s.name: s.values for s in m.sensors}
        got = np.array([sensors[names[int(b)]][c] for b, c in zip(t.board, t.channel)])
        np.testing.assert_array_equal(got, f.astype(np.float32))
    assert forces.max() > 2.0  # the poke was felt
    states = msgs["/skinsafe/state"]  # every tick's, after its /skinsafe/tick
    assert len(states) == len(msgs["/skinsafe/tick"]) == len(msgs["/joint_states"])
    assert any(s.retracting and len(s.pool_taxels) for s in states)  # the layers' state names the taxels by id
    rec = Recording(folder)  # what the viewers read: the same ticks, the taxels by index in the map's order
    np.testing.assert_array_equal(rec.t, [m.t for m in msgs["/skinsafe/tick"]])
    for s, lay in zip(states, rec.layers):
        assert (lay.potential, lay.speed_factor, lay.retracting) == (s.potential, s.speed_factor, s.retracting)
        np.testing.assert_array_equal(t.ids[lay.pool], s.pool_taxels)
    np.testing.assert_array_equal(rec.forces, forces.astype(np.float32))
    assert any(m.msg.startswith("stopped: ") for m in msgs["/rosout"])


def test_mcap_ros2_support_decodes_every_message(run):
    folder, _, _ = run
    counts = {}
    with open(record_file(folder), "rb") as f:
        for _, channel, _, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            if channel.topic == "/skinsafe/tactile":
                assert msg.sensors and all(len(s.values) for s in msg.sensors)
    assert counts == {t: len(m) for t, m in rosbags_messages(folder).items()}


def test_the_skin_points_are_the_taxel_map_through_the_recorded_tf(run):
    folder, skin, _ = run
    msgs = rosbags_messages(folder)
    design = load(skin)
    tf = {stamp(m): m for m in msgs["/tf"]}
    static = links(msgs["/tf_static"][0])  # each taxel link on its body: the map's position and frame
    for i, tid in enumerate(design.taxels.ids):
        body, R, p = static[f"taxel_{tid}"]
        assert body == design.body_of(i)
        np.testing.assert_allclose(p, design.taxels.positions[i], atol=1e-12)
        np.testing.assert_allclose(R, design.taxels.frames[i], atol=1e-9)
    assert len(msgs["/skinsafe/skin"]) >= 10
    for m in msgs["/skinsafe/skin"]:
        poses = world_poses(tf[stamp(m)])
        expect = np.array([poses[design.body_of(i)][0] @ design.taxels.positions[i] + poses[design.body_of(i)][1]
                           for i in range(design.n_taxels)])
        np.testing.assert_allclose(cloud(m)[:, :3], expect, atol=2e-6)  # float32 metres


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-3.1, 3.1), min_size=6, max_size=6))
def test_every_taxel_is_where_the_tf_puts_it_at_any_pose(ur5, q):
    robot, design = ur5
    topics = Ros2Topics(robot.model, design, "<robot/>")
    force = np.arange(design.n_taxels, dtype=float)
    out = dict(topics.tick(Tick(t=1.0, q=np.array(q), command=np.zeros(6), force=force, force_new=True)))
    store = typestore()
    poses = world_poses(store.deserialize_cdr(out["/tf"], "tf2_msgs/msg/TFMessage"))
    points = cloud(store.deserialize_cdr(out["/skinsafe/skin"], "sensor_msgs/msg/PointCloud2"))
    kin = TaxelKinematics(robot.model, design)
    pos, _ = kin.poses(np.array(q))  # MuJoCo's own taxel positions
    np.testing.assert_allclose(points[:, :3], pos, atol=2e-6)
    np.testing.assert_array_equal(points[:, 3], force.astype(np.float32))
    for i in range(design.n_taxels):  # the taxel map through the TF tree
        R, p = poses[design.body_of(i)]
        np.testing.assert_allclose(R @ design.taxels.positions[i] + p, pos[i], atol=1e-9)


def test_foxglove_gets_what_the_record_holds(ur5, run):
    folder, skin, live = run
    msgs = rosbags_messages(folder)
    got = live["messages"]
    assert len(got["/tf"]) >= 5 and len(got["/skinsafe/tactile"]) >= 5 and got["/robot_description"]
    store = get_typestore(Stores.EMPTY)  # the types from what the server advertised, as Foxglove reads them
    for topic in LIVE:
        c = live["channels"][topic]
        assert (c["encoding"], c["schemaEncoding"]) == ("cdr", "ros2msg")
        store.register(get_types_from_msg(c["schema"], c["schemaName"]))
    assert store.deserialize_cdr(got["/robot_description"][0][1], "std_msgs/msg/String").data == \
        msgs["/robot_description"][0].data
    q = {stamp(m): m.position for m in msgs["/joint_states"]}
    model = ur5[0].model
    data = mujoco.MjData(model)
    for _, raw in got["/tf"]:  # each link where MuJoCo puts it at the recorded joint state of the same tick
        m = store.deserialize_cdr(raw, "tf2_msgs/msg/TFMessage")
        data.qpos[:] = q[stamp(m)]
        mujoco.mj_kinematics(model, data)
        poses = world_poses(m)
        for b in range(1, model.nbody):
            R, p = poses[model.body(b).name]
            np.testing.assert_allclose(p, data.xpos[b], atol=1e-12)
            np.testing.assert_allclose(R, data.xmat[b].reshape(3, 3), atol=1e-9)
    rec = Recording(folder)  # the record's ticks: the forces the layers saw (float64), newest by each tick
    design = load(skin)
    names = {b.id: b.name for b in design.boards}
    for _, data in got["/skinsafe/tactile"]:
        m = store.deserialize_cdr(data, "tactile_msgs/msg/TactileState")
        i = int(np.argmin(np.abs(rec.t - stamp(m))))
        assert abs(rec.t[i] - stamp(m)) < 1e-9  # a tick of the record
        sensors = {s.name: s.values for s in m.sensors}
        values = np.array([sensors[names[int(b)]][c] for b, c in zip(design.taxels.board, design.taxels.channel)])
        np.testing.assert_array_equal(values, rec.tick(i).force.astype(np.float32))


def test_the_docs_layout_is_the_one_built_and_shows_recorded_topics():
    doc = json.loads((Path(__file__).parents[2] / "docs/run/skinsafe.foxglove.json").read_text())
    assert doc == layout()
    text = json.dumps(doc)
    shown = set(re.findall(r'"(/[a-z_/]+)', text))
    assert shown == {"/robot_description", "/skinsafe/robot_meshes", "/skinsafe/skin", "/skinsafe/contacts",
                     "/skinsafe/state", "/rosout"}
    assert shown <= set(TOPICS)
    fields = set(re.findall(r"/skinsafe/state\.([a-z_]+)", text))  # the plotted fields are LayerState's
    assert fields == {"potential", "speed_factor", "retracting"}
    assert fields <= {name for name, _ in typestore().fielddefs["skinsafe_msgs/msg/LayerState"][1]}


def test_the_writer_process_behind_gets_every_tick_and_a_killed_one_is_named(ur5, tmp_path):
    """The record's writer process (core/app/record_writer.py) paused while the loop puts more ticks than its ring holds:
    the ticks beyond the ring lose their telemetry (counted) and their safety topics wait in the loop's backlog, so
    the record holds every tick in order, the stop's last; a writer killed mid-run is named at close, never waited on,
    and what it had written is recovered into a folder rosbags opens."""
    import signal

    from skinsafe.core.app.record_writer import start

    robot, design = ur5
    save(design, tmp_path / "skin.json")
    joints = [robot.model.joint(j).name for j in range(robot.model.njnt)]

    def feed(folder):
        return start(folder, tmp_path / "skin.json", joints, [b.uid for b in design.boards], design.n_taxels,
                     {"map": str(tmp_path / "skin.json"), "period_s": 0.001})

    def tick(i, last=False):
        return Tick(t=i * 1e-3, q=np.full(len(joints), i * 1e-3), command=np.zeros(len(joints)), index=i + 1,
                    force=np.full(design.n_taxels, float(i)), force_new=True, reading_seq=float(i), ticked=not last,
                    stop="stopped" if last else "", ns=10**6 * (i + 1))

    rec = feed(tmp_path / "run")
    os.kill(rec.proc.pid, signal.SIGSTOP)
    k = rec.frames.slots + 40
    for i in range(k):
        rec.put(tick(i, last=i == k - 1))
    assert rec.dropped == 40 and len(rec.backlog) == 40
    os.kill(rec.proc.pid, signal.SIGCONT)
    out = rec.close({"reason": "stopped", "kind": "fault", "dropped": rec.dropped})
    assert out["dropped"] == 40 and out["path"] == str(tmp_path / "run"), out
    got = Recording(tmp_path / "run")
    assert np.allclose(got.t, np.arange(k) * 1e-3) and np.allclose(got.q[:, 0], np.arange(k) * 1e-3)
    assert len(got.forces) == k - 40 and np.allclose(got.forces[:, 0], np.arange(k - 40))  # the ring's ticks' forces
    assert got.stop == "stopped"

    rec = feed(tmp_path / "killed")  # killed mid-run: what it wrote is recovered into the folder
    k = 600  # ~3 MiB of messages, the forces random (LZ4 keeps their size): chunks of 1 MiB reach the disk
    part = tmp_path / "killed.part" / "killed_0.mcap"
    forces = np.random.default_rng(0).random((k, design.n_taxels))
    for i in range(k):
        while not rec.frames.room():
            time.sleep(0.001)
        rec.put(Tick(t=i * 1e-3, q=np.full(len(joints), i * 1e-3), command=np.zeros(len(joints)), index=i + 1,
                     force=forces[i], force_new=True, reading_seq=float(i), ns=10**6 * (i + 1)))
    for _ in range(3000):  # at least two chunks written (a writer that never writes fails below)
        if part.stat().st_size > 1_500_000:
            break
        time.sleep(0.01)
    os.kill(rec.proc.pid, signal.SIGKILL)
    out = rec.close({"reason": "stopped", "kind": "fault"})
    assert f"writer process (pid {rec.proc.pid}) died (killed by signal 9)" in out["error"]
    assert out["recovered"] == str(tmp_path / "killed") in out["error"] and not part.parent.exists()
    msgs = rosbags_messages(tmp_path / "killed")  # a finished rosbag2 folder: every message it holds decodes
    ticks = [m.index for m in msgs["/skinsafe/tick"]]
    assert out["written"] == sum(map(len, msgs.values())) and 300 < len(ticks) < k
    assert ticks == list(range(1, len(ticks) + 1))  # every tick up to the recovered end, in order
    np.testing.assert_array_equal([m.position[0] for m in msgs["/joint_states"][:len(ticks)]], np.arange(len(ticks)) * 1e-3)
    got = Recording(tmp_path / "killed")  # each recovered tick's forces as the loop gave them
    np.testing.assert_array_equal(got.forces, forces[:len(ticks)].astype(np.float32))

    rec = feed(tmp_path / "orphan")  # the run died with its writer (nobody closed it): the next run recovers it
    for i in range(k // 2):
        while not rec.frames.room():
            time.sleep(0.001)
        rec.put(Tick(t=i * 1e-3, q=np.zeros(len(joints)), command=np.zeros(len(joints)), index=i + 1, force=forces[i],
                     force_new=True, reading_seq=float(i), ns=10**6 * (i + 1)))
    for _ in range(3000):  # chunks of ticks written, beyond the first's latched topics (the URDF alone fills one)
        if (tmp_path / "orphan.part" / "orphan_0.mcap").stat().st_size > 1_500_000:
            break
        time.sleep(0.01)
    os.kill(rec.proc.pid, signal.SIGKILL)
    rec.proc.wait()
    rec.frames.close()
    rec = feed(tmp_path / "orphan")
    (kept,) = tmp_path.glob("orphan-recovered-*")
    assert rec.recovered_part == {"path": str(kept), "written": sum(map(len, rosbags_messages(kept).values()))}
    assert len(Recording(kept).t) > 100
    rec.put(tick(0, last=True))
    assert rec.close({"reason": "stopped", "kind": "end"})["path"] == str(tmp_path / "orphan")
    assert len(Recording(tmp_path / "orphan").t) == 1


def test_the_robots_meshes_are_triangle_markers_on_their_links():
    """A robot's visual mesh (its colliding sphere left to the URDF) as a TRIANGLE_LIST locked to its link, at the geom's
    pose, its triangles MuJoCo's; a large mesh decimated to the budget; rosbags decodes both."""
    from skinsafe.core.runtime.ros2_msgs import triangle_markers
    from skinsafe.core.runtime.ros2_topics import mesh_markers

    xml = """<mujoco><asset><mesh name="t" vertex="0 0 0 1 0 0 0 1 0 0 0 1"/>{big}</asset><worldbody>
      <body name="link" pos="0 0 1"><joint/><geom type="mesh" mesh="t" pos="0.1 0.2 0" euler="0 0 90" contype="0"
      conaffinity="0"/><geom size="0.1"/>{big_geom}</body></worldbody></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml.format(big="", big_geom=""))
    store = typestore()
    got = store.deserialize_cdr(triangle_markers(0.0, mesh_markers(model)), "visualization_msgs/msg/MarkerArray")
    (m,) = got.markers
    assert (m.header.frame_id, m.type, m.frame_locked) == ("link", 11, True)
    p, o = m.pose.position, m.pose.orientation
    np.testing.assert_allclose([p.x, p.y, p.z, o.w, o.x, o.y, o.z], np.r_[model.geom_pos[0], model.geom_quat[0]])
    points = np.array([[q.x, q.y, q.z] for q in m.points])
    np.testing.assert_allclose(points, model.mesh_vert[model.mesh_face].reshape(-1, 3), atol=1e-6)
    lat, lon = np.meshgrid(np.linspace(0.05, np.pi - 0.05, 40), np.linspace(0, 2 * np.pi, 90, endpoint=False),
                           indexing="ij")  # a band of a sphere: 40 x 90 vertices, 2 triangles per cell
    v = np.stack([np.sin(lat) * np.cos(lon), np.sin(lat) * np.sin(lon), np.cos(lat)], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(39), np.arange(90), indexing="ij")
    a, b, c, d = i * 90 + j, i * 90 + (j + 1) % 90, (i + 1) * 90 + j, (i + 1) * 90 + (j + 1) % 90
    f = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    mesh = f'<mesh name="big" vertex="{" ".join(map(str, v.ravel().round(5)))}" face="{" ".join(map(str, f.ravel()))}"/>'
    model = mujoco.MjModel.from_xml_string(xml.format(big=mesh, big_geom=(
        '<geom type="mesh" mesh="big" contype="0" conaffinity="0"/>')))
    big = mesh_markers(model, triangles=1000)
    assert model.mesh_facenum.sum() > 7000 and sum(len(x[5]) for x in big) < 1100
    assert len(store.deserialize_cdr(triangle_markers(0.0, big), "visualization_msgs/msg/MarkerArray").markers) == 2
    again, finer = mesh_markers(model, triangles=1000), mesh_markers(model, triangles=3000)  # the cache, by budget
    assert all(np.array_equal(x[5], y[5]) for x, y in zip(big, again, strict=True))
    assert sum(len(x[5]) for x in finer) > 2000

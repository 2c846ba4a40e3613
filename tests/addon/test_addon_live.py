"""Blender's live link (addon/live.py), headless: attached through its operator to a real view stream (the
runtime's ViewPublisher on a socket), stepped by hand (bpy timers never fire headless). A touch on taxel i
changes that taxel's colour to the scale's colour of its force and no other taxel's, for any taxel of either
module and any force (hypothesis), with the stream's taxels in another order than the scene's and holding
taxels the scene lacks; the robot takes the streamed pose; a record opens and scrubs; Detach removes the timer."""
import subprocess
import sys
import time
from pathlib import Path

import bpy
import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import live
from skinsafe.addon.core_to_blender import srgb_to_linear
from skinsafe.core.runtime.sim_record import SimRecord
from skinsafe.core.runtime.tap import Tap
from skinsafe.core.runtime.tick import Tick
from skinsafe.core.runtime.view_scale import colours
from skinsafe.core.runtime.view_stream import ViewPublisher, hello

E = 0.13585 - 0.1197  # UR5 forearm capsule axis height (body frame)
PICTURE = Path(__file__).resolve().parents[2] / "results" / "view" / "blender_live.png"  # the README's
VMAX = 4.0  # the scale's top: twice the 2 N threshold


def _place(body, anchor, direction=(-1, 0, 0), **settings):
    s = bpy.context.scene.skinsafe.new_module
    for k, v in {"template": "rect", "rows": 8, "cols": 8, "pitch": 0.01, "taxel_diameter": 0.006, "margin": 0.002,
                 "min_bend_radius": 0.01, "method": "geodesic", **settings}.items():
        setattr(s, k, v)
    assert bpy.ops.skinsafe.place_module(body=body, anchor=anchor, direction=direction, use_cursor=False) == {"FINISHED"}


@pytest.fixture(scope="module")
def scene():
    bpy.ops.wm.read_homefile(use_empty=True)
    b2c.clear_caches()
    bpy.ops.skinsafe.import_robot(source="ur5")
    _place("forearm_link", (-0.25, 0, E + 0.05))
    _place("upper_arm_link", (-0.2, 0, 0.13585 + 0.06), rows=4, cols=6)
    return bpy.context.scene


def _corners(scene) -> np.ndarray:
    """(taxels, 6, 4) `live` colours of the scene's taxels in design order."""
    design = b2c.design_of(scene)
    out = np.zeros((design.n_taxels, 6, 4), np.float32)
    for obj in b2c.module_objects(scene):
        on = np.flatnonzero(design.taxels.module == obj.skinsafe_module.module_id)
        attr = obj.data.color_attributes[live.ATTR]
        c = np.empty(len(attr.data) * 4, np.float32)
        attr.data.foreach_get("color", c)
        out[on] = c.reshape(-1, 6, 4)
    return out


def _expected(f: float) -> np.ndarray:
    """The linear colour of force f (sent as float32, as the stream and a record's reader carry it)."""
    return srgb_to_linear(colours(np.array([f], np.float32), VMAX)[0] / 255.0)


@pytest.fixture(scope="module")
def stream(scene):
    """A publisher whose taxels are the scene's in a shuffled order plus 7 the scene lacks; yields send(force)."""
    design = b2c.design_of(scene)
    rng = np.random.default_rng(3)
    ids = np.concatenate([design.taxels.ids, design.taxels.ids.max() + 1 + np.arange(7)])
    order = rng.permutation(len(ids))
    robot = b2c.robot_for(scene)
    names = [robot.model.joint(j).name for j in range(robot.model.njnt)]
    tap = Tap()
    pub = ViewPublisher(tap.latest, hello(len(ids), ids[order], names, {}), port=0)
    at = {int(i): k for k, i in enumerate(ids[order])}
    clock = [0.0]

    def send(force_by_design_index: dict, q=None):
        """Publish one frame (forces of scene taxels by design index), step until the add-on applied it."""
        force = np.zeros(len(ids))
        for i, f in force_by_design_index.items():
            force[at[int(design.taxels.ids[i])]] = f
        clock[0] += 0.01
        tap.publish(Tick(t=clock[0], q=robot.home if q is None else q, force=force, command=np.zeros(6)))
        deadline = time.monotonic() + 10
        while live._link.last is None or live._link.last["t"] != pytest.approx(clock[0]):
            live.step(scene)
            assert time.monotonic() < deadline, "the frame never reached the add-on"
            time.sleep(0.005)

    assert bpy.ops.skinsafe.live_attach(source=f"127.0.0.1:{pub.address[1]}") == {"FINISHED"}
    assert bpy.app.timers.is_registered(live._timer)
    yield send
    if live._link is not None:  # a record test may have attached (and detached) since: Detach needs a link
        assert bpy.ops.skinsafe.live_detach() == {"FINISHED"}
    assert not bpy.app.timers.is_registered(live._timer)  # else the bpy process hangs at exit
    pub.close()


@settings(max_examples=25, deadline=None)
@given(data=st.data())
def test_a_touch_on_taxel_i_colours_that_taxel_and_no_other(scene, stream, data):
    n = b2c.design_of(scene).n_taxels
    i = data.draw(st.integers(0, n - 1), label="taxel")
    f = data.draw(st.floats(0.25, 3 * VMAX), label="force N")
    stream({})
    before = _corners(scene)
    assert np.allclose(before[:, :, :3], _expected(0.0), atol=1e-6) and np.all(before[:, :, 3] == 1.0)  # at rest
    stream({i: f})
    after = _corners(scene)
    changed = np.flatnonzero(np.abs(after - before).max(axis=(1, 2)) > 0)
    assert changed.tolist() == [i]
    assert np.allclose(after[i, :, :3], _expected(f), atol=1e-6) and np.all(after[i, :, 3] == 1.0)


def test_the_robot_takes_the_streamed_pose(scene, stream):
    robot = b2c.robot_for(scene)
    q = robot.home + np.array([0.3, -0.2, 0.4, 0.1, -0.3, 0.2])
    stream({}, q)
    bpy.context.view_layer.update()
    d = mujoco.MjData(robot.model)
    d.qpos[:] = q
    mujoco.mj_kinematics(robot.model, d)
    W = np.array(b2c.body_objects(scene)["wrist_3_link"].matrix_world)
    assert np.allclose(W[:3, 3], d.xpos[robot.model.body("wrist_3_link").id], atol=1e-5)
    stream({}, robot.home)


def _hot(png) -> int:
    """Pixels of the scale's colours above the threshold (red to yellow, lit: red well over blue) in the picture,
    left of its key (add_key: the render is the left 1 / 1.22 of the keyed picture)."""
    from PIL import Image

    a = np.asarray(Image.open(png).convert("RGB")).astype(int)
    a = a[:, :int(a.shape[1] / 1.22) - 2]
    return int(((a[..., 0] > 150) & (a[..., 0] - a[..., 2] > 80)).sum())


def test_a_touch_shows_in_the_rendered_picture_of_the_skin(scene, stream, tmp_path):
    """Workbench renders the live colours (the README's picture): a hand-sized press on the forearm, its centre
    at the scale's top, falling off over 2.5 cm, turns hot pixels where there were none at rest."""
    from skinsafe.addon.headless import render

    design = b2c.design_of(scene)
    on = np.flatnonzero(design.taxels.module == design.taxels.module[0])
    p = design.taxels.positions[on]
    centre = on[np.argmin(np.linalg.norm(p - p.mean(0), axis=1))]  # the middle of the module
    d = np.linalg.norm(p - design.taxels.positions[centre], axis=1)
    press = {int(i): float(VMAX * 1.5 * max(0.0, 1 - r / 0.025)) for i, r in zip(on, d) if r < 0.025}
    robot = b2c.robot_for(scene)
    pose = robot.home + np.array([0.5, -0.4, 0.6, -0.3, 0.4, 0.0])
    stream({}, pose)
    rest = render(scene, tmp_path / "rest.png", "live", size=700, vmax=VMAX)
    stream(press, pose)
    touched = render(scene, PICTURE, "live", size=700, vmax=VMAX)
    assert _hot(rest) == 0 and _hot(touched) > 100  # a taxel's hexagon is ~60 pixels at this size
    stream({}, robot.home)


def test_a_record_opens_and_scrubs_to_the_touch(scene, tmp_path):
    design = b2c.design_of(scene)
    robot = b2c.robot_for(scene)
    names = [robot.model.joint(j).name for j in range(robot.model.njnt)]
    j = design.n_taxels - 3  # an upper-arm taxel
    rec = SimRecord(tmp_path / "touch.mcap", design, names, 0.02)
    for k in range(30):
        force = np.zeros(design.n_taxels)
        force[j] = 5.0 if 10 <= k < 15 else 0.0
        rec.tick(k * 0.02, robot.home, np.zeros(6), force=force)
    rec.close()
    assert live.attach(scene, str(tmp_path / "touch.mcap")).startswith("attached")
    cold = _corners(scene)
    assert live._link.record is not None and np.allclose(cold[:, :, :3], _expected(0.0), atol=1e-6)
    bpy.context.window_manager.skinsafe_live.time = 0.24  # the slider's callback shows tick 12
    hot = _corners(scene)
    changed = np.flatnonzero(np.abs(hot - cold).max(axis=(1, 2)) > 0)
    assert changed.tolist() == [j] and np.allclose(hot[j, :, :3], _expected(5.0), atol=1e-6)
    lv = bpy.context.window_manager.skinsafe_live
    lv.playing = True
    live.step(scene)
    time.sleep(0.2)
    live.step(scene)
    assert lv.time > 0.24 + 0.1  # playing follows the wall clock
    live.detach(scene)
    assert not bpy.app.timers.is_registered(live._timer)


def test_a_records_obstacles_are_drawn_and_move_with_its_ticks(scene, tmp_path):
    """An experiment's record: a ball that moves (a pose every tick), a box that stands where the metadata puts it,
    and a kind the views do not draw; each drawn with its MuJoCo size; Detach removes them."""
    design = b2c.design_of(scene)
    robot = b2c.robot_for(scene)
    names = [robot.model.joint(j).name for j in range(robot.model.njnt)]
    obstacles = [{"kind": "sphere", "size": [0.05], "pos": [0.4, 0.0, 0.3]},
                 {"kind": "box", "size": [0.1, 0.2, 0.05], "pos": [0.0, 0.5, 0.1], "quat": [0.7071068, 0, 0, 0.7071068]},
                 {"kind": "mesh", "size": [1.0], "pos": [0.0, 0.0, 0.0]}]
    rec = SimRecord(tmp_path / "balls.mcap", design, names, 0.02, "tracking", obstacles)
    for k in range(20):
        ball = [0.4, 0.01 * k, 0.3, 1, 0, 0, 0]
        rec.tick(k * 0.02, robot.home, np.zeros(6), force=np.zeros(design.n_taxels),
                 obstacles=[ball, obstacles[1]["pos"] + obstacles[1]["quat"], [0, 0, 0, 1, 0, 0, 0]])
    rec.close()
    assert live.attach(scene, str(tmp_path / "balls.mcap")).startswith("attached")
    col = bpy.data.collections[live.OBSTACLES]
    assert len(col.objects) == 2 and live._link.obstacles[2] is None
    ball, box = live._link.obstacles[:2]

    def extent(obj):
        v = np.array([obj.matrix_world @ x.co for x in obj.data.vertices])
        return v.min(0), v.max(0)
    bpy.context.view_layer.update()
    lo, hi = extent(ball)
    assert np.allclose((lo + hi) / 2, [0.4, 0.0, 0.3], atol=2e-3) and np.allclose(hi - lo, 0.1, atol=2e-3)
    lo, hi = extent(box)  # turned 90 degrees about z: its 0.1 x 0.2 half sizes swap
    assert np.allclose(hi - lo, [0.4, 0.2, 0.1], atol=1e-4) and np.allclose((lo + hi) / 2, [0.0, 0.5, 0.1], atol=1e-4)
    bpy.context.window_manager.skinsafe_live.time = 0.2  # tick 10: the ball 10 cm along y
    bpy.context.view_layer.update()
    lo, hi = extent(ball)
    assert np.allclose((lo + hi) / 2, [0.4, 0.1, 0.3], atol=2e-3)
    live.detach(scene)
    assert live.OBSTACLES not in bpy.data.collections and not any(o.name.startswith("obstacle") for o in bpy.data.objects)


def test_the_live_link_imports_nothing_the_addon_does_not_bundle():
    """Its stream client and colour scale: stdlib and numpy only (no mujoco, torch, numba, mcap)."""
    code = ("import sys; import skinsafe.core.runtime.view_stream, skinsafe.core.runtime.view_scale; "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'mujoco', 'torch', 'numba', 'mcap', 'scipy', 'bpy'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"

"""What a run says to ROS 2 tools and Foxglove: the robot on /tf, its skin placed and coloured by force, the
layers' state and their faults, each tick turned into ROS 2 messages (core/runtime/ros2_msgs.py).

| topic | type | when | frame |
| --- | --- | --- | --- |
| `/robot_description` | std_msgs/String | once (transient local) | the URDF with a link `taxel_<id>` per taxel |
| `/tf_static` | tf2_msgs/TFMessage | once (transient local) | each `taxel_<id>` on its link (z: outward normal) |
| `/skinsafe/robot_meshes` | visualization_msgs/MarkerArray | once (transient local) | the robot's mesh geoms (the URDF holds its primitives, not its meshes) as triangle lists on their links |
| `/tf` | tf2_msgs/TFMessage | `rate_hz` | each link on its parent link; the root links on `world` |
| `/skinsafe/tactile` | tactile_msgs/TactileState | `rate_hz` | one sensor per board (its name), values by channel (N; NaN: no taxel): the newest reading |
| `/skinsafe/skin` | sensor_msgs/PointCloud2 | `rate_hz` | `world`: x, y, z, force (N) of every taxel |
| `/skinsafe/contacts` | sensor_msgs/PointCloud2 | `rate_hz` | `world`: x, y, z, force, priority (0 first) of the taxels the layers retract from |
| `/skinsafe/state` | skinsafe_msgs/LayerState | every tick (the record writes it: `state`) | danger potential, speed factor, retracting, the taxel ids retracted from, flags, stop |
| `/rosout` | rcl_interfaces/Log | on a change of the layers' flags (WARN), on the stop (WARN) | |

`world` is the MuJoCo model's world (the robot's base); stamps are the robot's clock. The rate is counted on
the robot's clock, so a record holds the same messages however fast it was written; `every=True` (the live
stream, which samples ticks) gives every topic of the tick, `/skinsafe/state` included.
"""
from __future__ import annotations

import functools

import mujoco
import numpy as np

from skinsafe.core.robot.array_cache import load_pieces, save_pieces
from skinsafe.core.robot.kinematics import body_ids, taxel_quats
from skinsafe.core.runtime import ros2_msgs as msgs
from skinsafe.core.runtime.tick import Tick
from skinsafe.core.skin.model import SkinDesign

TOPICS = {"/robot_description": "std_msgs/msg/String", "/tf_static": "tf2_msgs/msg/TFMessage",
          "/tf": "tf2_msgs/msg/TFMessage", "/skinsafe/robot_meshes": "visualization_msgs/msg/MarkerArray", "/skinsafe/tactile": "tactile_msgs/msg/TactileState",
          "/skinsafe/skin": "sensor_msgs/msg/PointCloud2", "/skinsafe/contacts": "sensor_msgs/msg/PointCloud2",
          "/skinsafe/state": "skinsafe_msgs/msg/LayerState", "/rosout": "rcl_interfaces/msg/Log"}
LATCHED = ("/robot_description", "/tf_static", "/skinsafe/robot_meshes")  # transient local: a late subscriber gets them
MESH_RGBA = (0.7, 0.7, 0.72, 1.0)
MESH_TRIANGLES = 20_000  # the robot's meshes decimated to about this many triangles in all (72 bytes each)
WORLD = "world"
SKIN_FIELDS = ("x", "y", "z", "force")
CONTACT_FIELDS = ("x", "y", "z", "force", "priority")
RATE_HZ = 30.0


def _relative(qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
    """conj(qa) * qb for quaternions (B, 4) w x y z, as x y z w: b's rotation in a's frame."""
    w1, x1, y1, z1 = qa[:, 0], -qa[:, 1], -qa[:, 2], -qa[:, 3]
    w2, x2, y2, z2 = qb.T
    return np.column_stack([w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2, w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2, w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2])


def mesh_markers(model: mujoco.MjModel, triangles: int = MESH_TRIANGLES) -> list[tuple]:
    """The robot's mesh geoms as `msgs.triangle_markers` markers on their bodies: its visual ones (no contacts), or
    its colliding ones where it has none (as exporters/urdf.py chooses), decimated (core/robot/meshes.py) to about
    `triangles` in all, each mesh its share by its own count."""
    g = np.arange(model.ngeom)
    on_body = model.geom_bodyid[g] > 0
    visual = on_body & (model.geom_contype[g] == 0) & (model.geom_conaffinity[g] == 0)
    chosen = g[(visual if visual.any() else on_body) & (model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH)]
    if not len(chosen):  # a robot of primitives: skin_collision (scipy.spatial, ~0.23 CPU s) stays unloaded
        return []
    from skinsafe.core.sim.skin_collision import geom_digest

    key = "markers-" + geom_digest(model, chosen, triangles)  # decimated once per robot (seconds), then from the cache
    tris = load_pieces(key)
    if tris is None or len(tris) != len(chosen):
        tris = _decimated(model, chosen, triangles)
        save_pieces(key, [t.reshape(-1, 3) for t in tris])
    return [(model.body(model.geom_bodyid[i]).name, "skinsafe/robot", int(i),
             np.concatenate([model.geom_pos[i], model.geom_quat[i]]), MESH_RGBA, t.reshape(-1, 3, 3))
            for i, t in zip(chosen, tris)]


def _decimated(model: mujoco.MjModel, chosen: np.ndarray, triangles: int) -> list[np.ndarray]:
    """Each chosen mesh geom's triangles (k, 3, 3), decimated to its share of `triangles` by its own count."""
    import trimesh

    from skinsafe.core.robot.meshes import decimate

    total = max(1, int(model.mesh_facenum[model.geom_dataid[chosen]].sum()))
    out = []
    for i in chosen:
        m = model.geom_dataid[i]
        v0, f0, nf = model.mesh_vertadr[m], model.mesh_faceadr[m], model.mesh_facenum[m]
        mesh = decimate(trimesh.Trimesh(model.mesh_vert[v0:v0 + model.mesh_vertnum[m]],
                                        model.mesh_face[f0:f0 + nf]), max(4, triangles * nf // total))  # vertices merged
        out.append(np.asarray(mesh.vertices)[np.asarray(mesh.faces)])
    return out


def state(k: Tick, ids: np.ndarray | None = None) -> bytes:
    """Tick k's skinsafe_msgs/LayerState, its retracting taxels named by `ids` (None: by index)."""
    pool = np.zeros(0, np.int64) if k.pool_taxels is None else np.asarray(k.pool_taxels, np.int64)
    return msgs.layer_state(k.t, k.potential, k.speed_factor, k.retracting, pool if ids is None else ids[pool],
                            k.flags, k.stop)


class Ros2Topics:
    """A run's ROS 2 messages (module docstring) for the robot `model` (its qpos: the tick's q) and `design`."""

    def __init__(self, model: mujoco.MjModel, design: SkinDesign, urdf: str, rate_hz: float = RATE_HZ):
        if not rate_hz > 0:
            raise ValueError(f"ROS 2 topics: rate {rate_hz} Hz must be positive")
        self.model, self.data, self.urdf, self.period = model, mujoco.MjData(model), urdf, 1.0 / rate_hz
        names = [model.body(b).name for b in range(model.nbody)]
        self.children = names[1:]
        self.parent_id = np.asarray(model.body_parentid[1:])
        self.parents = [WORLD if p == 0 else names[p] for p in self.parent_id]
        self.tf = msgs.TfEncoder(self.parents, self.children)
        t = design.taxels
        self.ids = np.asarray(t.ids)
        self.body = body_ids(model, design)[t.body] if len(t) else np.zeros(0, np.int64)
        self.local = np.asarray(t.positions, float)
        self.taxel_parents = [names[b] for b in self.body]
        self.taxel_quat = taxel_quats(t.frames)[:, [1, 2, 3, 0]]  # w, x, y, z -> ROS's x, y, z, w
        order = np.argsort(self.body, kind="stable")  # taxels by body: one product per body's slice
        self.inverse = None if (order == np.arange(len(order))).all() else np.argsort(order)
        self.local_by_body = self.local[order]
        bounds = np.flatnonzero(np.diff(self.body[order])) + 1
        self.groups = [(int(self.body[order[a]]), slice(a, b))
                       for a, b in zip([0, *bounds], [*bounds, len(order)]) if b > a]
        boards = sorted((b for b in design.boards if (t.board == b.id).any()), key=lambda b: b.id)
        self.board_names = [b.name for b in boards]  # /skinsafe/tactile's sensors, one per board by channel
        self.tactile = msgs.TactileEncoder(self.board_names, [int(t.channel[t.board == b.id].max()) + 1 for b in boards],
                                           np.searchsorted([b.id for b in boards], t.board), t.channel)
        self.due, self.flags, self.stopped = -np.inf, (), False

    def static(self, t: float = 0.0) -> list[tuple[str, bytes]]:
        """The latched messages: the URDF, the taxel links on their links, the robot's meshes."""
        return [("/robot_description", msgs.string_msg(self.urdf)),
                ("/tf_static", msgs.tf_message(t, self.taxel_parents, [f"taxel_{int(i)}" for i in self.ids],
                                               self.local, self.taxel_quat)),
                ("/skinsafe/robot_meshes", self.meshes)]

    @functools.cached_property
    def meshes(self) -> bytes:
        """`/skinsafe/robot_meshes`, decimated once (seconds for a robot of CAD meshes)."""
        return msgs.triangle_markers(0.0, mesh_markers(self.model))

    def links(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each body's pose on its parent at q: translations (B, 3), rotations (B, 4) x y z w."""
        d = self.data
        d.qpos[:] = q
        mujoco.mj_kinematics(self.model, d)
        p = self.parent_id
        R = d.xmat[p].reshape(-1, 3, 3)
        xyz = np.einsum("bji,bj->bi", R, d.xpos[1:] - d.xpos[p])
        return xyz, _relative(d.xquat[p], d.xquat[1:])

    def taxel_positions(self) -> np.ndarray:
        """The taxels' world positions (N, 3) at the q of the last `links`."""
        d, out = self.data, np.empty((len(self.body), 3))
        for b, rows in self.groups:
            np.matmul(self.local_by_body[rows], d.xmat[b].reshape(3, 3).T, out=out[rows])
            out[rows] += d.xpos[b]
        return out if self.inverse is None else out[self.inverse]

    def state(self, k: Tick) -> bytes:
        """Tick k's `/skinsafe/state`."""
        return state(k, self.ids)

    def tick(self, k: Tick, every: bool = False) -> list[tuple[str, bytes]]:
        """Tick k's messages (module docstring): at the rate, or all with `every`; `/skinsafe/state` only with
        `every` (a record writes it every tick)."""
        t, out = k.t, []
        pool = np.zeros(0, np.int64) if k.pool_taxels is None else np.asarray(k.pool_taxels, np.int64)
        if every or t >= self.due:
            self.due = t + self.period
            out.append(("/tf", self.tf(t, *self.links(k.q))))
            if k.force is not None:
                out.append(("/skinsafe/tactile", self.tactile(t, k.force)))
            pos = self.taxel_positions()
            force = np.zeros(len(pos)) if k.force is None else np.nan_to_num(k.force)
            skin = np.empty((len(pos), 4), np.float32)
            skin[:, :3], skin[:, 3] = pos, force
            contacts = np.empty((len(pool), 5), np.float32)
            contacts[:, :4], contacts[:, 4] = skin[pool], np.arange(len(pool))
            out += [("/skinsafe/skin", msgs.point_cloud(t, WORLD, SKIN_FIELDS, skin)),
                    ("/skinsafe/contacts", msgs.point_cloud(t, WORLD, CONTACT_FIELDS, contacts))]
            if every:
                out.append(("/skinsafe/state", self.state(k)))
        if k.flags != self.flags:
            self.flags = k.flags
            out.append(("/rosout", msgs.log(t, msgs.LOG_WARN, "skinsafe/layers",
                                            "flags: " + (", ".join(k.flags) or "none"))))
        if k.stop and not self.stopped:
            self.stopped = True
            out.append(("/rosout", msgs.log(t, msgs.LOG_WARN, "skinsafe/monitor", f"stopped: {k.stop}")))
        return out

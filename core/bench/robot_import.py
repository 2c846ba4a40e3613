"""`skinsafe bench import`: a robot in, a full-arm skin designed on it, and whether the skin
sits on the robot's real surface and feels where it sits.

One row per robot (the built-ins and the bundled Franka description), each run in a fresh
process so `peak_mb` is that robot's own peak resident memory:
`robot`, `links` (skinned), `triangles_in` (mesh triangles of the skinned links as described),
`triangles_used` (in their design surfaces), `import_s` (load the robot and build the surfaces),
`design_s` (place the modules), `taxels`, `peak_mb`,
`taxel_to_surface_mm_worst` (to the link's visual surface as described, not decimated),
`taxel_to_collision_mm_worst` (to the contact surface of the scene, `collision="skin"`),
`contact_recall` (random pokes 3 mm deep on skinned surfaces that light the nearest taxel),
`self_contacts_home` (robot-robot contacts at the home pose).
"""
from __future__ import annotations

import multiprocessing as mp
import resource
import time
from pathlib import Path

import numpy as np

ASSET = Path(__file__).resolve().parents[2] / "blend_assets" / "franka_description"
FRANKA = ("urdf", "franka", str(ASSET / "robots" / "panda" / "panda.urdf.xacro"), (str(ASSET),))
ROBOTS = {"ur5": ("builtin", "ur5", None, ()), "panda": ("builtin", "panda", None, ()), "franka": FRANKA}


def add_arguments(p) -> None:
    p.add_argument("--robots", default=",".join(ROBOTS), help=f"comma separated, of {', '.join(ROBOTS)}")
    p.add_argument("--pokes", type=int, default=400, help="random pokes per robot for contact_recall")
    p.add_argument("--pitch", type=float, default=0.012, help="taxel pitch of the 4x4 modules, m")


def skinnable_bodies(robot) -> list[str]:
    """Moving links with a real outer surface (the whole arm; see `surface_bodies`)."""
    from skinsafe.core.design.surface import surface_bodies

    return surface_bodies(robot.model, moving=True)


def design_arm(robot, ref, pitch: float = 0.012, bodies=None):
    """A full-arm skin of 4x4 modules tiled over every moving link; returns (design, surfaces)."""
    from skinsafe.core.design.layout import tile_body, without_buried
    from skinsafe.core.design.placement import build_design
    from skinsafe.core.design.surface import cached_surfaces
    from skinsafe.core.skin.model import Module

    bodies = bodies or skinnable_bodies(robot)
    surfaces = cached_surfaces(robot.model, bodies)
    template = Module(0, "tile", "", rows=4, cols=4, pitch=pitch, taxel_diameter=0.6 * pitch, margin=0.002,
                      min_bend_radius=0.02)
    placed = []
    for b in bodies:
        mine, _ = tile_body(surfaces[b], robot.model, template, b, len(placed))
        placed += mine
    design = build_design(ref, placed, capacity=512, bodies=[b for b in bodies if any(p.module.body == b for p in placed)])
    return without_buried(design, robot.model, robot.home)[0], surfaces


def pokes(model, data, design, surfaces, n: int, depth: float = 0.003, radius: float = 0.005, seed: int = 0):
    """Share of random pokes (a sphere pressed `depth` into a random point of a module's cells)
    that light the taxel nearest to the poked point."""
    import mujoco

    from skinsafe.core.sim.readout import SkinReadout

    rng = np.random.default_rng(seed)
    reader = SkinReadout(model, design)
    t = design.taxels
    pitch = {m.id: m.pitch for m in design.modules}
    probe = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "poke")
    mocap = model.body_mocapid[probe]
    lit = 0
    qpos = data.qpos.copy()
    for _ in range(n):
        i = int(rng.integers(len(t)))
        h = pitch[int(t.module[i])] / 2
        u, v = rng.uniform(-h, h, 2)
        body = design.bodies[int(t.body[i])]
        p, nrm, _, _ = surfaces[body].closest(t.positions[i] + u * t.frames[i, :, 0] + v * t.frames[i, :, 1])
        on = np.flatnonzero(t.body == t.body[i])
        near = on[np.argmin(np.linalg.norm(t.positions[on] - p[0], axis=1))]
        bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
        data.qpos[:] = qpos
        data.qvel[:] = 0
        mujoco.mj_kinematics(model, data)
        R, x = data.xmat[bid].reshape(3, 3), data.xpos[bid]
        data.mocap_pos[mocap] = R @ (p[0] + (radius - depth) * nrm[0]) + x
        mujoco.mj_forward(model, data)
        lit += bool(reader.read(data)[near] > 0)
    return lit / max(n, 1)


def self_contacts(model, data) -> int:
    """Penetrating contacts between two robot geoms (neither in the world body nor the probe)."""
    import mujoco

    skip = {0, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "poke")}
    return sum(1 for c in data.contact[:data.ncon]
               if c.dist < 0 and not {int(model.geom_bodyid[g]) for g in c.geom} & skip)


def robot_row(name: str, n_pokes: int, pitch: float) -> dict:
    import mujoco

    from skinsafe.core.design.surface import skin_geoms
    from skinsafe.core.robot.models import load_robot
    from skinsafe.core.sim.scene import Obstacle, build_scene
    from skinsafe.core.sim.skin_collision import taxel_clearance
    from skinsafe.core.skin.model import RobotRef

    ref = RobotRef(*ROBOTS[name])
    t0 = time.perf_counter()
    robot = load_robot(ref)
    bodies = skinnable_bodies(robot)
    from skinsafe.core.design.surface import cached_surfaces

    surfaces = cached_surfaces(robot.model, bodies)
    t1 = time.perf_counter()
    design, _ = design_arm(robot, ref, pitch, bodies)
    t2 = time.perf_counter()
    m = robot.model
    tri_in = sum(int(m.mesh_facenum[m.geom_dataid[g]]) for b in bodies for g in skin_geoms(m, m.body(b).id)
                 if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH)
    tri_used = sum(len(surfaces[b].triangles) for b in bodies)
    # distance to the visual surface as described (meshes at full resolution)
    from skinsafe.core.design.surface import body_surface

    to_surface = 0.0
    for bi, b in enumerate(design.bodies):
        on = design.taxels.body == bi
        full = body_surface(m, b, budget=10 ** 9)
        to_surface = max(to_surface, float(full.closest(design.taxels.positions[on])[3].max()))
    poke = Obstacle("poke", "sphere", (0.005,), pos=(0, 0, -5), mocap=True)
    spec = build_scene(design, robot, [poke])
    clearance = taxel_clearance(spec, design, robot.home)
    model = spec.compile()
    data = mujoco.MjData(model)
    data.qpos[:] = robot.home
    # servos hold the home pose and gravity is off: a poke's contact force is then its own
    model.opt.gravity[:] = 0
    data.ctrl[:] = robot.home[model.jnt_qposadr[model.actuator_trnid[:, 0]]] if model.nu else 0
    mujoco.mj_forward(model, data)
    home_contacts = self_contacts(model, data)
    recall = pokes(model, data, design, surfaces, n_pokes)
    return dict(robot=name, links=len(design.bodies), triangles_in=tri_in, triangles_used=tri_used,
                import_s=t1 - t0, design_s=t2 - t1, taxels=design.n_taxels,
                peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                taxel_to_surface_mm_worst=to_surface * 1e3,
                taxel_to_collision_mm_worst=float(np.abs(clearance).max()) * 1e3,
                contact_recall=recall, self_contacts_home=home_contacts)


def _child(name, n_pokes, pitch, queue):
    import os

    os.environ.setdefault("OMP_NUM_THREADS", "1")
    try:
        queue.put(robot_row(name, n_pokes, pitch))
    except Exception as e:  # reported in the parent as a failed row
        queue.put({"robot": name, "error": f"{type(e).__name__}: {e}"})


def rows(args) -> list[dict]:
    from tqdm import tqdm

    out = []
    ctx = mp.get_context("spawn")
    for name in tqdm([r for r in str(args.robots).split(",") if r], desc="bench import"):
        if name not in ROBOTS:
            raise SystemExit(f"skinsafe bench import: robot '{name}' is unknown; use one of {', '.join(ROBOTS)}")
        q = ctx.Queue()
        p = ctx.Process(target=_child, args=(name, args.pokes, args.pitch, q))
        p.start()
        out.append(q.get())
        p.join()
    return out

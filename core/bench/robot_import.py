"""`skinsafe bench import`: a robot in, a full-arm skin designed on it, and whether the skin
sits on the robot's real surface, feels where it sits, and the robot collides where it is.

One row per robot (the built-ins, the bundled and fetched public descriptions by name, and any
URDF, xacro or MJCF given with `--robot PATH`), each run in a fresh process so `peak_mb` is that
robot's own peak resident memory:
`robot`, `links` (skinned) and `skinned_links` (their names), `triangles_in` (mesh triangles of the skinned links' visual surfaces
as described), `triangles_used` (in their design surfaces), `import_s` (load the robot and build
the surfaces), `design_s` (place the modules), `taxels`, `peak_mb`,
`taxel_to_surface_mm_worst` (to the link's visual surface as described, not decimated),
`taxel_to_collision_mm_worst` (to the contact surface of the scene, `collision="skin"`),
`coverage_min` (the smallest covered fraction of a skinned arm link's area, `coverage_report`),
`bare_collision_mm_worst` / `bare_collision_mm_p90` (|distance| from points on the exposed
surface of every moving link without skin to the scene's contact surface),
`contact_recall` (random pokes 3 mm deep on skinned surfaces that light the nearest taxel),
`self_contacts_home` (robot-robot contacts at the home pose).
"""
from __future__ import annotations

import multiprocessing as mp
import resource
import time
from pathlib import Path

import numpy as np

from skinsafe.core.robot.catalog import DESCRIPTIONS, description
from skinsafe.core.robot.models import BUILTIN
from skinsafe.core.robot.urdf_import import parse_xacro_args
from skinsafe.core.skin.model import DesignError, RobotRef

ROBOTS = [*BUILTIN, *DESCRIPTIONS]  # by name
BARE_POINTS = 400  # exposed surface points per moving link for bare_collision_mm_*


def add_arguments(p) -> None:
    p.add_argument("--robots", default=",".join(ROBOTS), help=f"comma separated, of {', '.join(ROBOTS)} ('' for none)")
    p.add_argument("--robot", action="append", default=[], metavar="PATH",
                   help="also any URDF, xacro or MJCF file (repeatable), with --package-dir and --xacro-arg")
    p.add_argument("--package-dir", action="append", default=[], help="ROS package folder for --robot (repeatable)")
    p.add_argument("--xacro-arg", action="append", default=[], metavar="NAME:=VALUE", help="xacro argument for --robot")
    p.add_argument("--pokes", type=int, default=400, help="random pokes per robot for contact_recall")
    p.add_argument("--pitch", type=float, default=0.012, help="taxel pitch of the 4x4 modules, m")


def robot_ref(robot: str, package_dirs=(), xacro_args: dict | None = None) -> RobotRef:
    """A built-in or catalogue name, or a robot file (kind from its suffix, paths made absolute)."""
    if robot in BUILTIN:
        return RobotRef("builtin", robot)
    if robot in DESCRIPTIONS:
        return description(robot)
    path = Path(robot)
    if not path.is_file():
        raise DesignError(f"bench import: robot '{robot}' is neither a name ({', '.join(ROBOTS)}) nor a file; "
                          "give a URDF, xacro or MJCF path")
    kind = "mjcf" if path.suffix.lower() in (".xml", ".mjcf") else "urdf"
    return RobotRef(kind, path.name.split(".")[0], str(path.resolve()),
                    tuple(str(Path(d).resolve()) for d in package_dirs), dict(xacro_args or {}))


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


def bare_points(model, design, q, n: int = BARE_POINTS, seed: int = 0) -> dict[str, np.ndarray]:
    """Body name -> `n` random points (body frame) on the exposed surface (`exposed_triangles`;
    the built-ins' primitives where a robot has no visual mesh) of each moving link without skin."""
    from skinsafe.core.design.surface import body_surface, surface_bodies
    from skinsafe.core.sim.skin_collision import exposed_triangles

    rng = np.random.default_rng(seed)
    exposed = exposed_triangles(model, q)
    out = {}
    for name in surface_bodies(model, moving=True):
        if name in design.bodies:
            continue
        tri = exposed.get(name)
        if tri is None:
            surf = body_surface(model, name)
            tri = surf.vertices[surf.triangles]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        if not len(tri) or area.sum() <= 0:
            continue
        k = rng.choice(len(tri), n, p=area / area.sum())
        out[name] = np.einsum("kj,kjd->kd", rng.dirichlet([1, 1, 1], n), tri[k])
    return out


def robot_row(robot: str | RobotRef, n_pokes: int, pitch: float) -> dict:
    import mujoco

    from skinsafe.core.design.coverage import coverage_report
    from skinsafe.core.design.surface import body_surface, cached_surfaces, skin_geoms
    from skinsafe.core.robot.models import load_robot
    from skinsafe.core.sim.scene import Obstacle, build_scene
    from skinsafe.core.sim.skin_collision import point_clearance, taxel_clearance

    ref = robot_ref(robot) if isinstance(robot, str) else robot
    t0 = time.perf_counter()
    robot = load_robot(ref)
    bodies = skinnable_bodies(robot)
    surfaces = cached_surfaces(robot.model, bodies)
    t1 = time.perf_counter()
    design, _ = design_arm(robot, ref, pitch, bodies)
    t2 = time.perf_counter()
    m = robot.model
    skinned = design.bodies  # rows count the skinned links only
    tri_in = sum(int(m.mesh_facenum[m.geom_dataid[g]]) for b in skinned for g in skin_geoms(m, m.body(b).id)
                 if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH)
    tri_used = sum(len(surfaces[b].triangles) for b in skinned)
    to_surface = 0.0  # distance to the visual surface as described (meshes at full resolution)
    for bi, b in enumerate(skinned):
        on = design.taxels.body == bi
        full = body_surface(m, b, budget=10 ** 9)
        to_surface = max(to_surface, float(full.closest(design.taxels.positions[on])[3].max()))
    cover = coverage_report(design, m)
    arm = [b for b in skinned if m.body_weldid[m.body(b).id] != 0]
    poke = Obstacle("poke", "sphere", (0.005,), pos=(0, 0, -5), mocap=True)
    spec = build_scene(design, robot, [poke])
    clearance = taxel_clearance(spec, design, robot.home)
    bare = np.concatenate(list(point_clearance(spec, bare_points(m, design, robot.home), robot.home).values())
                          or [np.zeros(0)])
    bare = np.abs(bare[np.isfinite(bare)])
    model = spec.compile()
    data = mujoco.MjData(model)
    data.qpos[:] = robot.home
    # servos hold the home pose and gravity is off: a poke's contact force is then its own
    model.opt.gravity[:] = 0
    data.ctrl[:] = robot.home[model.jnt_qposadr[model.actuator_trnid[:, 0]]] if model.nu else 0
    mujoco.mj_forward(model, data)
    home_contacts = self_contacts(model, data)
    recall = pokes(model, data, design, surfaces, n_pokes)
    return dict(robot=ref.name, links=len(skinned), skinned_links=" ".join(skinned), triangles_in=tri_in, triangles_used=tri_used,
                import_s=t1 - t0, design_s=t2 - t1, taxels=design.n_taxels,
                peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                taxel_to_surface_mm_worst=to_surface * 1e3,
                taxel_to_collision_mm_worst=float(np.abs(clearance).max()) * 1e3,
                coverage_min=float(min(cover[b]["fraction"] for b in arm)) if arm else float("nan"),
                bare_collision_mm_worst=float(bare.max()) * 1e3 if len(bare) else float("nan"),
                bare_collision_mm_p90=float(np.percentile(bare, 90)) * 1e3 if len(bare) else float("nan"),
                contact_recall=recall, self_contacts_home=home_contacts)


def _child(ref, n_pokes, pitch, queue):
    import os

    os.environ.setdefault("OMP_NUM_THREADS", "1")
    try:
        queue.put(robot_row(ref, n_pokes, pitch))
    except Exception as e:  # reported in the parent as a failed row
        queue.put({"robot": ref.name, "error": f"{type(e).__name__}: {e}"})


def rows(args) -> list[dict]:
    from tqdm import tqdm

    try:
        args_x = parse_xacro_args(args.xacro_arg, "--xacro-arg")
        refs = [robot_ref(r) for r in str(args.robots).split(",") if r]
        refs += [robot_ref(r, args.package_dir, args_x) for r in args.robot]
    except DesignError as e:
        raise SystemExit(f"skinsafe bench import: {e}") from None
    out = []
    ctx = mp.get_context("spawn")
    for ref in tqdm(refs, desc="bench import"):
        q = ctx.Queue()
        p = ctx.Process(target=_child, args=(ref, args.pokes, args.pitch, q))
        p.start()
        out.append(q.get())
        p.join()
    return out

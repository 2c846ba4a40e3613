"""`skinsafe bench import`: a robot in, its arm covered with skin (`cover_design`), and whether the
skin sits on the robot's real surface, feels where it sits, and the robot collides where it is.

One row per robot (the built-ins, the bundled and fetched public descriptions by name, and any
URDF, xacro or MJCF given with `--robot PATH`), each run in a fresh process so `peak_mb` is that
robot's own peak resident memory:
`robot`, `links` (skinned) and `skinned_links` (their names), `triangles_in` (mesh triangles of the skinned links' visual surfaces
as described), `triangles_used` (in their design surfaces), `import_s` (load the robot and build
the surfaces), `design_s` (cover every moving link: 3x3 modules at `--pitch`), `taxels`, `peak_mb`,
`taxel_to_surface_mm_worst` (to the link's visual surface as described, not decimated),
`taxel_to_collision_mm_worst` (to the contact surface of the scene, `collision="skin"`),
`coverage_min` (the smallest covered fraction of an arm link's open surface: its area less what
lies inside another link at home or behind its own internal faces, `cover_report`; a moving link
left bare counts 0) with `coverage_min_link` (which link), `coverage_of_link_min` (the same over
each link's whole surface),
`bare_collision_mm_worst` / `bare_collision_mm_p90` (|distance| from points on the exposed
surface of every moving link without skin to the scene's contact surface),
`skinned_bare_collision_mm_worst` / `_p90` (the same from the exposed surface of the skinned links
outside their taxel cells),
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
    p.add_argument("--pitch", type=float, default=0.01, help="taxel pitch of the 3x3 cover modules, m")


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


def bare_points(model, design, q, n: int = BARE_POINTS, seed: int = 0, skinned: bool = False) -> dict[str, np.ndarray]:
    """Body name -> `n` random points (body frame) on the exposed surface (`exposed_triangles`;
    the built-ins' primitives where a robot has no visual mesh) of each moving link without skin,
    or with `skinned`, of each skinned link outside its taxel cells (`Footprint`)."""
    from skinsafe.core.design.surface import body_surface, surface_bodies
    from skinsafe.core.sim.skin_collision import Footprint, exposed_triangles

    rng = np.random.default_rng(seed)
    exposed = exposed_triangles(model, q)
    out = {}
    for name in surface_bodies(model, moving=True):
        if (name in design.bodies) != skinned:
            continue
        tri = exposed.get(name)
        if tri is None:
            surf = body_surface(model, name)
            tri = surf.vertices[surf.triangles]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        if not len(tri) or area.sum() <= 0:
            continue
        m = 20 * n if skinned else n  # most of a covered link's surface is under its cells
        k = rng.choice(len(tri), m, p=area / area.sum())
        pts = np.einsum("kj,kjd->kd", rng.dirichlet([1, 1, 1], m), tri[k])
        if skinned:
            pts = pts[~Footprint.of(design, name).near(pts, 0.0)][:n]
        if len(pts):
            out[name] = pts
    return out


def _abs_finite(gaps: dict) -> np.ndarray:
    d = np.concatenate(list(gaps.values()) or [np.zeros(0)])
    return np.abs(d[np.isfinite(d)])


def robot_row(robot: str | RobotRef, n_pokes: int, pitch: float) -> dict:
    import mujoco

    from skinsafe.core.design.cover import cover_design, cover_report
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
    design, _ = cover_design(robot, ref, bodies, pitch=pitch, surfaces=surfaces)
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
    report = cover_report(design, m, robot.home)
    arm = [b for b in bodies if m.body_weldid[m.body(b).id] != 0]  # a moving link left bare counts 0
    covered = {b: report[b]["covered"] if b in report else 0.0 for b in arm}
    least = min(covered, key=covered.get) if arm else ""
    poke = Obstacle("poke", "sphere", (0.005,), pos=(0, 0, -5), mocap=True)
    spec = build_scene(design, robot, [poke])
    clearance = taxel_clearance(spec, design, robot.home)
    bare = _abs_finite(point_clearance(spec, bare_points(m, design, robot.home), robot.home))
    skin_bare = _abs_finite(point_clearance(spec, bare_points(m, design, robot.home, skinned=True), robot.home))
    model = spec.compile()
    data = mujoco.MjData(model)
    data.qpos[:] = robot.home
    # servos hold the home pose and gravity is off: a poke's contact force is then its own
    model.opt.gravity[:] = 0
    data.ctrl[:] = robot.home[model.jnt_qposadr[model.actuator_trnid[:, 0]]] if model.nu else 0
    mujoco.mj_forward(model, data)
    home_contacts = self_contacts(model, data)
    recall = pokes(model, data, design, surfaces, n_pokes)
    worst = lambda d: float(d.max()) * 1e3 if len(d) else None  # noqa: E731 (None: no such link)
    p90 = lambda d: float(np.percentile(d, 90)) * 1e3 if len(d) else None  # noqa: E731 (None: no such link)
    return dict(robot=ref.name, links=len(skinned), skinned_links=" ".join(skinned), triangles_in=tri_in, triangles_used=tri_used,
                import_s=t1 - t0, design_s=t2 - t1, taxels=design.n_taxels, modules=len(design.modules),
                peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                taxel_to_surface_mm_worst=to_surface * 1e3,
                taxel_to_collision_mm_worst=float(np.abs(clearance).max()) * 1e3,
                coverage_min=covered[least] if arm else float("nan"), coverage_min_link=least,
                coverage_of_link_min=min((report[b]["covered_of_link"] if b in report else 0.0 for b in arm),
                                         default=float("nan")),
                bare_collision_mm_worst=worst(bare), bare_collision_mm_p90=p90(bare),
                skinned_bare_collision_mm_worst=worst(skin_bare), skinned_bare_collision_mm_p90=p90(skin_bare),
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

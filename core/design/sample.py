"""The sample skin: FPC grid modules wrapped around the capsule/cylinder link shapes of a
built-in robot (`skinsafe sample`), only where no joint housing (of the same link, or coaxial with
a joint to the next) covers the cells: a sample skin passes `skinsafe check`.

On a cylinder, wrapping is exact and geodesic: a module's rows run along the axis, its columns
around the circumference, at the module pitch in arc length. Taxel frames: x along a row
(around the link), y along the axis, z = the outward radial normal.
"""
from __future__ import annotations

import mujoco
import numpy as np

from skinsafe.core.design.coverage import coverage_report, format_report
from skinsafe.core.robot.models import BUILTIN, Robot, build_ur5
from skinsafe.core.robot.shapes import inside_depth
from skinsafe.core.skin.boards import assign_boards, number_channels
from skinsafe.core.skin.ids import stable_ids
from skinsafe.core.skin.model import DesignError, Module, RobotRef, SkinDesign, Taxels


def sample_bodies(model: mujoco.MjModel) -> list[str]:
    """The links a sample skin wraps, from the model's data: every link whose first geom (its main
    shape) is a capsule or cylinder and that at least two joints move (the link on the first joint only turns in place about the base's
    axis). On the UR5 upper_arm_link to wrist_3_link, on the Panda link2 to link7."""
    shapes = (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_CYLINDER))
    out = []
    for b in range(1, model.nbody):
        joints, a = 0, b
        while a:
            joints += int(model.body_jntnum[a])
            a = int(model.body_parentid[a])
        if joints >= 2 and model.body_geomnum[b] and int(model.geom_type[model.body_geomadr[b]]) in shapes:
            out.append(model.body(b).name)
    return out


def turned_poses(model: mujoco.MjModel, home: np.ndarray, turn: float = 2.1) -> list[mujoco.MjData]:
    """Kinematics at home and with every joint turned by +-`turn` (clipped to its limits): a cell
    covered at all three is under a housing coaxial with a joint (or of its own link)."""
    out = []
    for sign in (0.0, 1.0, -1.0):
        q = home.copy()
        for j in range(model.njnt):
            a = model.jnt_qposadr[j]
            if int(model.jnt_type[j]) in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
                q[a] += sign * turn
                if model.jnt_limited[j]:
                    q[a] = np.clip(q[a], *model.jnt_range[j])
        d = mujoco.MjData(model)
        d.qpos[:] = q
        mujoco.mj_kinematics(model, d)
        out.append(d)
    return out


def exposed_span(model: mujoco.MjModel, poses: list[mujoco.MjData], geom: int, pitch: float,
                 margin: float, phi: np.ndarray) -> tuple[float, float] | None:
    """The axial range (geom frame, m) of the cylindrical part of `geom` where no taxel cell lies
    inside another colliding geom at every one of `poses` (see `turned_poses`), at the angles `phi`
    around the axis (one column block of modules, cell edges included): the longest such run.
    Cells under a housing of the same link, or one coaxial with the joint to the next link, would be
    off the link's outer surface or buried at every pose (`skinsafe check` refuses both); a
    neighbour that only passes over the cells at some poses does not count. None where nothing is free."""
    r, half = model.geom_size[geom][:2]
    s = np.arange(-half + margin, half - margin + 1e-9, pitch / 4)  # candidate ring centres
    if not len(s):
        return None
    z = (s[:, None, None] + np.array([-pitch / 2, 0.0, pitch / 2])[None, :, None]) * np.ones_like(phi)
    local = np.stack([r * np.cos(phi) * np.ones_like(z), r * np.sin(phi) * np.ones_like(z), z], -1).reshape(-1, 3)
    covered = np.ones(len(local), bool)
    for data in poses:
        world = local @ data.geom_xmat[geom].reshape(3, 3).T + data.geom_xpos[geom]
        now = np.zeros(len(local), bool)
        for g in range(model.ngeom):
            if g == geom or not (model.geom_contype[g] or model.geom_conaffinity[g]):
                continue
            p = (world - data.geom_xpos[g]) @ data.geom_xmat[g].reshape(3, 3)
            now |= inside_depth(model, g, p) > 1e-4
        covered &= now
    free = ~covered.reshape(len(s), -1).any(axis=1)
    best, start = (0, 0), None
    for k, f in enumerate(np.append(free, False)):
        if f and start is None:
            start = k
        elif not f and start is not None:
            best = max(best, (k - start, start))
            start = None
    if not best[0]:
        return None
    n, first = best
    return float(s[first]), float(s[first + n - 1])


def wrap_cylinder(model: mujoco.MjModel, geom: int, pitch: float, rows: int, cols: int, margin: float,
                  first_module: int, body_index: int, body_name: str,
                  taxel_diameter: float, threshold: float, poses: list[mujoco.MjData] | None = None
                  ) -> tuple[list[Module], Taxels | None]:
    """Cover the cylindrical part of a capsule/cylinder geom with rows x cols modules: the whole
    part less `margin`, or with `poses`, each column block of modules on its `exposed_span`."""
    if int(model.geom_type[geom]) not in (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_CYLINDER)):
        raise DesignError(f"geom {model.geom(geom).name}: only capsules and cylinders can be wrapped")
    r, half = model.geom_size[geom][:2]
    n_around = int(np.floor(2 * np.pi * r / pitch))
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, model.geom_quat[geom])
    R = R.reshape(3, 3)
    c = model.geom_pos[geom]
    modules, parts = [], []
    mid = first_module
    lo, hi = -half + margin, half - margin  # one row grid for the whole part: blocks stay aligned
    n_along = int(np.floor((hi - lo) / pitch + 1e-9)) + 1 if hi >= lo else 0
    row_z = lo + np.arange(n_along) * pitch + (hi - lo - (n_along - 1) * pitch) / 2
    for c0 in range(0, max(n_around, 0), cols):
        k0, k1 = 0, n_along
        if poses is not None:
            last = min(c0 + cols, n_around) - 1
            edges = np.linspace(c0 - 0.5, last + 0.5, 3 * (last - c0 + 1) + 1) * pitch / r
            span = exposed_span(model, poses, geom, pitch, margin, edges)
            free = np.flatnonzero((row_z >= span[0] - 1e-9) & (row_z <= span[1] + 1e-9)) if span else []
            if not len(free):
                continue
            k0, k1 = int(free[0]), int(free[-1]) + 1
        for r0 in range(k0, k1, rows):
            ii, jj = np.meshgrid(np.arange(r0, min(r0 + rows, k1)), np.arange(c0, min(c0 + cols, n_around)),
                                 indexing="ij")
            ii, jj = ii.ravel(), jj.ravel()
            phi = jj * pitch / r  # the pitch in arc length: the FPC wraps without stretching
            z = row_z[ii]
            radial = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], 1)
            tangent = np.stack([-np.sin(phi), np.cos(phi), np.zeros_like(phi)], 1)
            axis = np.broadcast_to([0.0, 0.0, 1.0], radial.shape)
            local = r * radial + z[:, None] * axis
            frames = np.stack([tangent, axis, radial], axis=2)  # x around, y along, z out
            k = len(phi)
            parts.append(Taxels(
                ids=stable_ids(np.full(k, mid)),
                body=np.full(k, body_index, np.int32),
                positions=local @ R.T + c,
                frames=np.einsum("ij,njk->nik", R, frames),
                module=np.full(k, mid, np.int32),
                board=np.zeros(k, np.int32),
                channel=np.zeros(k, np.int32),
                area=np.full(k, np.pi * (taxel_diameter / 2) ** 2),
                enabled=np.ones(k, bool),
                thresholds={"force": np.full(k, threshold)},
            ))
            modules.append(Module(
                id=mid, name=f"{body_name}_m{mid - first_module}", body=body_name, template="rect",
                rows=int(ii.max() - r0 + 1), cols=int(jj.max() - c0 + 1), pitch=pitch,
                taxel_diameter=taxel_diameter, margin=min(margin, (pitch - taxel_diameter) / 2),  # FPCs abut
                min_bend_radius=min(0.01, r),
                placement={"method": "cylinder_wrap", "geom": model.geom(geom).name,
                           "row0": int(r0), "col0": int(c0), "n_around": n_around},
            ))
            mid += 1
    return modules, Taxels.concatenate(parts) if parts else None


def make_sample_design(robot_name: str = "ur5", pitch: float = 0.01, rows: int = 8, cols: int = 8,
                       board_capacity: int = 512, threshold: float = 2.0, robot: Robot | None = None) -> SkinDesign:
    """A skin of rows x cols modules on the main capsule of each sample body of a built-in robot."""
    if robot_name not in BUILTIN:
        raise DesignError(f"sample skin: robot '{robot_name}' is not a built-in ({', '.join(sorted(BUILTIN))}); "
                          "for any other robot (a URDF, xacro or MJCF file) use `skinsafe design ROBOT`")
    if not (0 < pitch < 1):
        raise DesignError(f"sample skin: pitch {pitch} m is outside (0, 1); use e.g. 0.01")
    robot = robot or BUILTIN[robot_name]()
    model = robot.model
    bodies: list[str] = []
    modules: list[Module] = []
    parts: list[Taxels] = []
    poses = turned_poses(model, robot.home)
    for name in sample_bodies(model):
        bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        geom = int(np.flatnonzero(model.geom_bodyid == bid)[0])
        ms, tx = wrap_cylinder(model, geom, pitch, rows, cols, margin=0.5 * pitch,
                               first_module=len(modules),
                               body_index=len(bodies), body_name=name, taxel_diameter=0.6 * pitch,
                               threshold=threshold, poses=poses)
        if tx is not None:  # a link whose capsule is all under housings carries no skin
            bodies.append(name)
            modules += ms
            parts.append(tx)
    taxels = Taxels.concatenate(parts)
    sizes = {m.id: int((taxels.module == m.id).sum()) for m in modules}
    boards, of = assign_boards(taxels.module, sizes, board_capacity)
    modules = [Module(**{**m.__dict__, "board": of[m.id]}) for m in modules]
    taxels.board = np.array([of[int(m)] for m in taxels.module], dtype=np.int32)
    taxels.channel = number_channels(taxels.module, taxels.board)
    design = SkinDesign(RobotRef("builtin", robot_name), bodies, modules, boards, taxels)
    design.coverage = coverage_report(design, model)
    design.validate("sample skin", robot.body_names)
    return design


def design_with(n: int, robot=None):
    """The sample UR5 skin resampled (pitch chosen, then cut or tiled) to exactly n taxels."""
    robot = robot or build_ur5()
    base = make_sample_design("ur5", robot=robot)
    idx = np.resize(np.arange(base.n_taxels), n)
    t = base.taxels.subset(np.sort(idx))
    t.ids = stable_ids(t.module)
    return base.with_taxels(t), robot


def add_arguments(p) -> None:
    p.add_argument("--robot", default="ur5", help=f"built-in robot ({', '.join(sorted(BUILTIN))}); "
                   "for a URDF/xacro/MJCF use `skinsafe design`")
    p.add_argument("--pitch", type=float, default=0.01, help="taxel pitch in m (default 0.01)")
    p.add_argument("--out", default="out/sample_skin.json", help="taxel map to write")


def run(args) -> int:
    from skinsafe.core.skin.taxel_map import save

    design = make_sample_design(args.robot, args.pitch)
    path = save(design, args.out)
    print(format_report(design.coverage))
    print(f"wrote {path} ({design.n_taxels} taxels, {len(design.modules)} modules, {len(design.boards)} boards)")
    return 0

"""Geometric audit of a skin design on its robot (what `skinsafe check` refuses), on the surfaces
the design was built on (`cached_surfaces`): taxels off their link's surface, module outlines
overhanging it, placement anchors far from it, modules that cannot be built (in-plane strain over
their FPC's tolerance, or pads the independent round trip does not confirm), and taxels buried
inside another link at every sampled pose (they can never be touched). `enclosed` finds points on internal faces of a link's
own mesh; the designers never place skin there."""
from __future__ import annotations

import mujoco
import numpy as np

from skinsafe.core.design.placement import FAR_ANCHOR, module_grid
from skinsafe.core.design.strain import module_strain
from skinsafe.core.design.surface import cached_surfaces, surface_bodies
from skinsafe.core.skin.model import SkinDesign

SURFACE_TOL = 0.002  # m
BURIED_TOL = 1e-4  # m: a taxel deeper than this inside another link is buried (coincident faces pass)


def sample_poses(model: mujoco.MjModel, home: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """`n` joint configurations: home, then uniform inside the limits of limited hinge/slide joints."""
    rng = np.random.default_rng(seed)
    q = np.repeat(home[None], n, axis=0)
    for j in range(model.njnt):
        if model.jnt_limited[j] and int(model.jnt_type[j]) in (int(mujoco.mjtJoint.mjJNT_HINGE),
                                                               int(mujoco.mjtJoint.mjJNT_SLIDE)):
            lo, hi = model.jnt_range[j]
            q[1:, model.jnt_qposadr[j]] = rng.uniform(lo, hi, n - 1)
    return q


def audit(design: SkinDesign, model: mujoco.MjModel, home: np.ndarray, poses: int = 16,
          tol: float = SURFACE_TOL) -> list[str]:
    """Every problem found, one readable line each (empty: the design passes)."""
    t = design.taxels
    surfaces = cached_surfaces(model, list(design.bodies))
    pitch = {m.id: m.pitch for m in design.modules}
    bend = {m.id: m.min_bend_radius for m in design.modules}
    problems = []
    for bi, body in enumerate(design.bodies):
        on = np.flatnonzero(t.body == bi)
        if not len(on):
            continue
        surf = surfaces[body]
        d = surf.closest(t.positions[on])[3]
        for i in on[d > tol][:5]:
            problems.append(f"taxel {int(t.ids[i])} on '{body}' is {d[np.searchsorted(on, i)] * 1e3:.1f} mm off the "
                            f"link's surface (more than {tol * 1e3:.1f} mm); re-place module {int(t.module[i])}")
        h = np.array([pitch.get(int(m), 0.01) / 2 for m in t.module[on]])
        r = np.array([bend.get(int(m), 0.01) for m in t.module[on]])
        worst = outline_overhang(surf, t.positions[on], t.frames[on], h, r)
        for m in np.unique(t.module[on][worst > tol]):
            k = int(np.argmax(np.where(t.module[on] == m, worst, -1)))
            problems.append(f"module {int(m)} on '{body}': its outline overhangs the link by {worst[k] * 1e3:.1f} mm at "
                            f"taxel {int(t.ids[on[k]])} (the FPC would stand off the surface); move it inward or use a "
                            "smaller module")
    for m in design.modules:
        anchor = m.placement.get("anchor") if isinstance(m.placement, dict) else None
        if anchor is not None and m.body in surfaces:
            gap = float(surfaces[m.body].closest(np.asarray(anchor, float).reshape(1, 3))[3][0])
            if gap > FAR_ANCHOR:
                problems.append(f"module {m.id} on '{m.body}': placement anchor is {gap * 1e3:.0f} mm from the link's "
                                f"surface (more than {FAR_ANCHOR * 1e3:.0f} mm); re-place the module on the link")
    problems += strain_problems(design) + roundtrip_problems(design, model)
    buried = buried_taxels(design, model, home, poses)
    if buried.any():
        i = int(np.argmax(buried))
        problems.append(f"{int(buried.sum())} taxels are buried more than {BURIED_TOL * 1e3:.1f} mm inside another link "
                        f"at all {poses} sampled poses "
                        f"(first: taxel {int(t.ids[i])} on '{design.bodies[t.body[i]]}', module {int(t.module[i])}); "
                        "they can never be touched: move those modules away from the joint")
    return problems


def module_strains(design: SkinDesign) -> dict[int, tuple[float, str] | None]:
    """Per module id: its largest in-plane strain and where (`strain.module_strain` of its taxels
    against its flat pattern), or None where its taxels do not match its template's pads."""
    t = design.taxels
    out = {}
    for m in design.modules:
        on = np.flatnonzero(t.module == m.id)
        grid = module_grid(m, len(on))
        if grid is None:
            out[m.id] = None
            continue
        s = module_strain(*grid, t.positions[on], t.frames[on, :, 2])
        k = s.worst
        where = "" if k < 0 else f"taxels {int(t.ids[on[s.a[k]]])} and {int(t.ids[on[s.b[k]]])}"
        out[m.id] = (s.max, where)
    return out


def strain_problems(design: SkinDesign, show: int = 10) -> list[str]:
    """A line per module that cannot be built as placed: in-plane strain over its `max_strain`
    (worst first; `show` of them, then a count), or taxels that are not its template's pads."""
    mods = {m.id: m for m in design.modules}
    strains = module_strains(design)
    odd = [i for i, v in strains.items() if v is None]
    over = sorted(((v[0], i, v[1]) for i, v in strains.items() if v is not None and v[0] > mods[i].max_strain),
                  reverse=True)
    lines = [f"module {i} '{mods[i].name}' on '{mods[i].body}': in-plane strain {s * 100:.1f}% between {where} is over "
             f"the FPC's {mods[i].max_strain * 100:.1f}% (a flat circuit cannot be wrapped there); re-place it smaller, "
             "cut its outline to the patch, or re-run the design" for s, i, where in over[:show]]
    if len(over) > show:
        lines.append(f"... and {len(over) - show} more modules over their strain tolerance "
                     f"({len(over)} of {len(mods)})")
    lines += [f"module {i} '{mods[i].name}': its {int((design.taxels.module == i).sum())} taxels are not the pads of its "
              f"{mods[i].template} {mods[i].rows}x{mods[i].cols} template, so its flat pattern is unknown; re-place it"
              for i in odd[:show]]
    return lines


def roundtrip_problems(design: SkinDesign, model: mujoco.MjModel, show: int = 10) -> list[str]:
    """A line per module whose pads are farther than `roundtrip.TOL` from where an independent wrap of
    its flat pattern puts them (worst first; `show` of them, then a count)."""
    from skinsafe.core.design.roundtrip import TOL, roundtrip

    mods = {m.id: m for m in design.modules}
    off = sorted(((float(r.error.max()), r.module) for r in roundtrip(design, model) if r.error.max() > TOL),
                 reverse=True)
    lines = [f"module {i} '{mods[i].name}' on '{mods[i].body}': an independent wrap of its flat pattern puts a pad "
             f"{e * 1e3:.1f} mm from the map's (over {TOL * 1e3:.0f} mm: the built circuit's pads would not be where "
             "the map says); re-place it off the crease or crack it lies over" for e, i in off[:show]]
    if len(off) > show:
        lines.append(f"... and {len(off) - show} more modules whose pads the independent wrap does not confirm")
    return lines


def outline_overhang(surface, positions, frames, half, min_bend) -> np.ndarray:
    """(N,) how far (m) each taxel cell's corners stand off the surface beyond the sag a cell of
    half-side `half` may show when bent at `min_bend` (0: the cell lies on the surface)."""
    half, min_bend = np.broadcast_to(half, len(positions)), np.broadcast_to(min_bend, len(positions))
    sag = 2 * half ** 2 / np.maximum(min_bend, 1e-3)
    corners = np.concatenate([positions + (sx * half)[:, None] * frames[:, :, 0] + (sy * half)[:, None] * frames[:, :, 1]
                              for sx in (-1, 1) for sy in (-1, 1)])
    return np.maximum((surface.closest(corners)[3].reshape(4, -1) - sag).max(axis=0), 0.0)


def buried_taxels(design: SkinDesign, model: mujoco.MjModel, home: np.ndarray, poses: int = 16,
                  depth: float = BURIED_TOL) -> np.ndarray:
    """(N,) True where a taxel lies more than `depth` inside another link's surface at every pose."""
    t = design.taxels
    surfaces = cached_surfaces(model, surface_bodies(model))
    body_id = np.array([model.body(b).id for b in design.bodies])[t.body] if len(t) else np.zeros(0, int)
    data = mujoco.MjData(model)
    always = np.ones(len(t), bool)
    for q in sample_poses(model, home, poses):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        world = np.einsum("nij,nj->ni", data.xmat[body_id].reshape(-1, 3, 3), t.positions) + data.xpos[body_id]
        always &= buried_points(model, data, surfaces, world, body_id, depth, always)
        if not always.any():
            break
    return always


def _cones(n: np.ndarray) -> np.ndarray:
    """(N, 13, 3): each unit normal n, then six directions 45 degrees off it and six grazing ones
    80 degrees off it, evenly around."""
    t = np.cross(n, np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(n, t)
    a = np.linspace(0, 2 * np.pi, 6, endpoint=False)[None, :, None]
    around = np.cos(a) * t[:, None] + np.sin(a) * b[:, None]
    tilt = np.radians([45.0, 80.0])
    return np.concatenate([n[:, None]] + [np.cos(e) * n[:, None] + np.sin(e) * around for e in tilt], axis=1)


def enclosed(model: mujoco.MjModel, data: mujoco.MjData, body: str, world: np.ndarray, normals: np.ndarray,
             lift: float = 1e-3) -> np.ndarray:
    """(N,) True where no ray from `lift` above a surface point of `body` (world frame, pose of
    `data`), along its normal or 45 or 80 degrees off it, leaves the body's own skin geoms: the
    point is on an internal face of the link's mesh (CAD visuals often carry them) or at the bottom
    of a pocket; either way no skin there can be touched."""
    from skinsafe.core.design.surface import skin_geoms

    geoms = skin_geoms(model, model.body(body).id)
    mesh = int(mujoco.mjtGeom.mjGEOM_MESH)

    def hits(p, v) -> bool:
        for g in geoms:
            if int(model.geom_type[g]) == mesh:
                d = mujoco.mj_rayMesh(model, data, g, p, v)
            else:
                d = mujoco.mju_rayGeom(data.geom_xpos[g], data.geom_xmat[g], model.geom_size[g], p, v,
                                       int(model.geom_type[g]))
            if d >= 0:
                return True
        return False

    out = np.zeros(len(world), bool)
    starts, cones = world + lift * normals, _cones(normals)
    for i in range(len(world)):
        out[i] = all(hits(starts[i], v) for v in cones[i])
    return out


def enclosed_taxels(design: SkinDesign, model: mujoco.MjModel, home: np.ndarray) -> np.ndarray:
    """(N,) True where a taxel is `enclosed` by its own link (pose-independent; computed at home)."""
    t = design.taxels
    data = mujoco.MjData(model)
    data.qpos[:] = home
    mujoco.mj_kinematics(model, data)
    out = np.zeros(len(t), bool)
    for bi, body in enumerate(design.bodies):
        on = np.flatnonzero(t.body == bi)
        b = model.body(body).id
        R, x = data.xmat[b].reshape(3, 3), data.xpos[b]
        out[on] = enclosed(model, data, body, t.positions[on] @ R.T + x, t.frames[on, :, 2] @ R.T)
    return out


def buried_points(model: mujoco.MjModel, data: mujoco.MjData, surfaces: dict, world: np.ndarray,
                  body_id: np.ndarray, depth: float = BURIED_TOL, only: np.ndarray | None = None) -> np.ndarray:
    """(N,) True where a point (world frame, riding on body `body_id`) lies more than `depth` inside
    the surface of a body of `surfaces` not welded to its own, in the pose of `data` (kinematics
    done); only the points `only` are tested."""
    weld = model.body_weldid
    body_id = np.broadcast_to(body_id, (len(world),))
    now = np.zeros(len(world), bool)
    todo = np.ones(len(world), bool) if only is None else only.copy()
    for name, surf in surfaces.items():
        b = model.body(name).id
        cand = np.flatnonzero(todo & ~now & (weld[body_id] != weld[b]))
        if not len(cand):
            continue
        R, x = data.xmat[b].reshape(3, 3), data.xpos[b]
        local = (world[cand] - x) @ R
        inside_box = ((local > surf.lo) & (local < surf.hi)).all(axis=1)
        near, local = cand[inside_box], local[inside_box]
        if not len(near):
            continue
        qp, n, _, d = surf.closest(local)
        now[near] |= (np.sum((local - qp) * n, axis=1) < -depth) & (d < 0.05)
    return now

"""A collision model where the skin is (`SceneOptions(collision="skin")`, the default).

Chosen by measurement, per skinned link (the link and the links welded to it):
1. every taxel's signed distance to the link's colliding geoms is measured with MuJoCo's own
   `mj_geomDistance` (a point probe; negative inside);
2. a coarse geom (one that is not a skin surface itself: a collision hull, an inflated
   self-collision capsule) burying taxels deeper than `tol` is shrunk until it sits under the skin
   (primitives by their sizes, meshes by moving every face of their convex hull inward);
3. where taxels are still farther than `tol` from the contact surface, each module becomes thin
   convex shells (blocks of its taxel cells and a copy `shell_depth` below them) on the link.

Links whose own geoms already carry the skin (the built-in capsules) are left as they are.
"""
from __future__ import annotations

import mujoco
import numpy as np
from scipy.spatial import ConvexHull, HalfspaceIntersection

from skinsafe.core.design.surface import skin_geoms
from skinsafe.core.robot.shapes import inside_depth, mesh_vertices
from skinsafe.core.skin.model import SkinDesign

PROBE = "skinsafe_probe"
SHELL_GROUP = 3


def _collides(model, g) -> bool:
    return bool(model.geom_contype[g] or model.geom_conaffinity[g])


def taxel_clearance(spec: mujoco.MjSpec, design: SkinDesign, q=None) -> np.ndarray:
    """(N,) signed distance (m) of each taxel to the contact surface of its link: the smallest
    `mj_geomDistance` to the colliding geoms of the link and the links welded to it (negative:
    buried inside one, by at least that much). Infinite where the link has no colliding geom."""
    s = spec.copy()
    probe = s.worldbody.add_body(name=PROBE, mocap=True)
    probe.add_geom(name=PROBE, type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[1e-6, 0, 0], contype=0, conaffinity=0)
    model = s.compile()
    data = mujoco.MjData(model)
    if q is not None:
        data.qpos[:len(q)] = q
    mujoco.mj_kinematics(model, data)
    pg = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, PROBE)
    t = design.taxels
    out = np.full(len(t), np.inf)
    fromto = np.zeros(6)
    for bi, name in enumerate(design.bodies):
        bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        weld = model.body_weldid[bid]
        geoms = [g for g in range(model.ngeom) if g != pg and _collides(model, g)
                 and model.body_weldid[model.geom_bodyid[g]] == weld]
        idx = np.flatnonzero(t.body == bi)
        world = t.positions[idx] @ data.xmat[bid].reshape(3, 3).T + data.xpos[bid]
        for i, p in zip(idx, world):
            data.geom_xpos[pg] = p  # mj_geomDistance reads the pose from here: no kinematics per taxel
            for g in geoms:
                out[i] = min(out[i], mujoco.mj_geomDistance(model, data, g, pg, 0.05, fromto))
    return out


def fit_to_skin(spec: mujoco.MjSpec, design: SkinDesign, tol: float = 1e-3, shell_depth: float = 0.003) -> dict:
    """Edit `spec` so every taxel is within `tol` of the contact surface (see the module doc).
    Returns {"shrunk": geom names, "disabled": geom names, "shells": count}."""
    report = {"shrunk": [], "disabled": [], "shells": 0}
    for k, g in enumerate(spec.geoms):  # unnamed geoms (URDF primitives) get names to be edited by
        if not g.name:
            g.name = f"{g.parent.name}_geom{k}"
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    t = design.taxels
    depth = taxel_clearance(spec, design)
    world = np.zeros((len(t), 3))
    for bi, name in enumerate(design.bodies):
        bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        on = t.body == bi
        world[on] = t.positions[on] @ data.xmat[bid].reshape(3, 3).T + data.xpos[bid]
    weld_of = {bi: model.body_weldid[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, b)]
               for bi, b in enumerate(design.bodies)}
    needs_shell = set()  # bodies whose coarse geoms were shrunk: all their modules get shells
    # a coarse robot geom (not itself a skin surface: a collision hull, an inflated self-collision
    # capsule) burying a taxel, of its own link or of a neighbour at the home pose, goes under the skin
    visual = {g for g in range(model.ngeom) if model.geom_bodyid[g] and not _collides(model, g)}
    surface = visual or {g for b in range(1, model.nbody) for g in skin_geoms(model, b)}
    for g in range(model.ngeom):
        if not _collides(model, g) or model.geom_bodyid[g] == 0 or g in surface:
            continue
        Rg, xg = data.geom_xmat[g].reshape(3, 3), data.geom_xpos[g]
        d = inside_depth(model, g, (world - xg) @ Rg)
        if d.max() > tol:
            _shrink(spec, model, g, float(d.max()) + 0.5e-3, report)
            weld = model.body_weldid[model.geom_bodyid[g]]
            needs_shell |= {bi for bi, w in weld_of.items() if w == weld}
    for m in design.modules:
        bi = design.bodies.index(m.body)
        if bi in needs_shell or (depth[t.module == m.id] > tol).any():  # taxels above the contact surface
            report["shells"] += _add_shell(spec, design, m, shell_depth)
    return report


def _shrink(spec, model, g, delta: float, report: dict) -> None:
    """Move geom g's surface inward by `delta` (drop it from contacts if nothing is left)."""
    sg = spec.geom(model.geom(g).name)
    G = mujoco.mjtGeom
    kind, size = int(model.geom_type[g]), model.geom_size[g].copy()
    sg.pos, sg.quat = model.geom_pos[g].tolist(), model.geom_quat[g].tolist()
    if kind == G.mjGEOM_MESH:
        v = mesh_vertices(model, g)
        eq = ConvexHull(v).equations.copy()
        c = v.mean(axis=0)
        eq[:, 3] += delta
        if (eq[:, :3] @ c + eq[:, 3]).max() >= -1e-4:
            sg.contype, sg.conaffinity = 0, 0
            report["disabled"].append(sg.name)
            return
        inner = HalfspaceIntersection(eq, c).intersections
        mesh = spec.add_mesh(name=f"{sg.name or 'geom'}_inset_{g}")
        mesh.uservert = inner.ravel().tolist()
        sg.meshname = mesh.name
        report["shrunk"].append(sg.name)
        return
    n = {G.mjGEOM_SPHERE: 1, G.mjGEOM_CAPSULE: 1, G.mjGEOM_CYLINDER: 2, G.mjGEOM_BOX: 3, G.mjGEOM_ELLIPSOID: 3}.get(kind)
    if n is None:
        return
    size[:n] -= delta
    if (size[:n] <= 1e-4).any():
        sg.contype, sg.conaffinity = 0, 0
        report["disabled"].append(sg.name)
        return
    sg.fromto = [np.nan] * 6
    sg.size = size.tolist()
    report["shrunk"].append(sg.name)


def _add_shell(spec, design: SkinDesign, module, depth: float, block: int = 2) -> int:
    """One module as thin convex collision shells on its link, one per `block` x `block` taxels
    (small pieces follow a curved FPC; one hull per module would bridge its hollows): each the
    taxel cells' corners and the same points `depth` below them (body frame). Returns the count."""
    t = design.taxels
    idx = np.flatnonzero(t.module == module.id)
    k = np.arange(len(idx))
    cols = max(module.cols, 1)
    piece = (k // cols) // block * (cols // block + 1) + (k % cols) // block
    h = module.pitch / 2
    count = 0

    def shell(sel):
        p, f = t.positions[sel], t.frames[sel]
        corners = [p + sx * h * f[:, :, 0] + sy * h * f[:, :, 1] for sx in (-1, 1) for sy in (-1, 1)]
        top = np.concatenate([p] + corners)
        return p, np.concatenate([top, top - depth * np.concatenate([f[:, :, 2]] * 5)])

    pieces = []
    for j in np.unique(piece):
        sel = idx[piece == j]
        p, pts = shell(sel)
        eq = ConvexHull(pts).equations
        # a block over a hollow buries its taxels under its hull: then one shell per taxel cell
        if len(sel) > 1 and (-(p @ eq[:, :3].T + eq[:, 3]).max(axis=1)).max() > 2e-4:
            pieces += [shell(sel[i:i + 1])[1] for i in range(len(sel))]
        else:
            pieces.append(pts)
    for pts in pieces:
        name = f"skin_shell_{module.id}_{count}"
        mesh = spec.add_mesh(name=name)
        mesh.uservert = pts.ravel().tolist()
        spec.body(module.body).add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_MESH, meshname=mesh.name,
                                        group=SHELL_GROUP, density=0, contype=1, conaffinity=1,
                                        rgba=[0.1, 0.7, 0.3, 0.25])
        count += 1
    return count

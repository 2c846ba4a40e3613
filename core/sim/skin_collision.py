"""A collision model where the surface is (`SceneOptions(collision="skin")`, the default), skinned
or not: at the exposed surface, and at the skin where the modules are.

Chosen by measurement:
1. every link whose visual surface is a mesh and that collides through other shapes (a collision
   hull, a CAD mesh MuJoCo would collide as its convex hull: 9-50 mm from the real surface over
   concave parts) collides instead through convex pieces cut from its exposed visual surface
   (`surface_pieces`: patches of the surface with their corners up to `PIECE_DEPTH` under them,
   thinned and split until no exposed point lies more than `PIECE_TOL` inside any piece); on a
   skinned link the pieces keep `FOOTPRINT_MARGIN` clear of its taxel cells and never come within
   `GUARD_GAP` of a cell or the space above it (`Footprint`): pieces cut from a decimated surface
   beside the cells stood mm above the taxels, and probes met them before the skin;
2. every taxel's signed distance to the link's colliding geoms is measured with MuJoCo's own
   `mj_geomDistance` (a point probe; negative inside);
3. a coarse geom left (one that is not a skin surface itself: an inflated self-collision
   capsule on a link without visual geometry) burying taxels deeper than `tol` is shrunk until it
   sits under the skin (primitives by their sizes, meshes by moving every face of their convex
   hull inward);
4. where taxels are still farther than `tol` from the contact surface (on every skinned link of
   1: its pieces leave the cells bare), each module becomes thin convex shells (blocks of its
   taxel cells and a copy `shell_depth` below them) on the link.

Links whose own geoms already carry the skin (the built-in capsules) are left as they are.
CoACD (convex decomposition) was measured for 1 and not taken: on the Gen3's links (3,000
triangles) it took 20-45 s per link and left surface points 18-32 mm inside its pieces (threshold
0.05); at 1,000 triangles without its preprocessing, 159 s and 392 pieces for one link.
"""
from __future__ import annotations

import mujoco
import numpy as np
from scipy.spatial import ConvexHull, HalfspaceIntersection

from skinsafe.core.design.surface import Surface, body_surface, skin_geoms
from skinsafe.core.robot.array_cache import load_pieces, save_pieces
from skinsafe.core.robot.shapes import inside_depth, mesh_vertices
from skinsafe.core.skin.model import SkinDesign

PROBE = "skinsafe_probe"
SHELL_GROUP = 3
PIECE_PREFIX = "surface_piece_"
PIECE_DEPTH = 0.005  # m: how far a surface piece reaches under the surface (less where the wall is thinner)
PIECE_BUDGET = 1500  # triangles of a link's outer surface the pieces are cut from
MIN_PIECE_DEPTH = 1.5e-3  # m: a piece is made thinner (down to this) before it is split
PIECE_TOL = 3e-3  # m: no outer surface point or taxel deeper than this inside a piece
PIECE_MIN_SIZE = 0.008  # m: pieces smaller than this are not split further
VOXEL = 0.002  # m: voxels that tell a link's outer surface from its hidden walls
FOOTPRINT_MARGIN = 2e-3  # m: on a skinned link, no piece is cut from the surface this close to a taxel cell
GUARD_GAP = 0.5e-3  # m: how close a piece may come to a taxel cell or the space 2 mm above it


class Footprint:
    """The taxel cells of one link (body frame): there the skin's shells are the contact surface,
    so surface pieces keep out (`surface_pieces`)."""

    def __init__(self, positions: np.ndarray, frames: np.ndarray, half: np.ndarray):
        from scipy.spatial import cKDTree

        self.positions, self.frames, self.half = positions, frames, half
        self.tree = cKDTree(positions)

    @classmethod
    def of(cls, design: SkinDesign, body: str) -> "Footprint | None":
        if body not in design.bodies:
            return None
        t = design.taxels
        on = t.body == design.bodies.index(body)
        pitch = {m.id: m.pitch for m in design.modules}
        return cls(t.positions[on], t.frames[on], 0.5 * np.array([pitch[int(k)] for k in t.module[on]]))

    def near(self, points: np.ndarray, margin: float, depth: float = PIECE_DEPTH) -> np.ndarray:
        """(k,) whether each point lies within `margin` of a taxel cell in its plane and within
        `depth` of it along its normal (either side)."""
        k = min(4, len(self.positions))
        _, idx = self.tree.query(points, k=k)
        idx = idx.reshape(len(points), k)
        local = np.einsum("pkd,pkdj->pkj", points[:, None] - self.positions[idx], self.frames[idx])
        lim = self.half[idx] + margin
        return ((np.abs(local[..., 0]) <= lim) & (np.abs(local[..., 1]) <= lim)
                & (np.abs(local[..., 2]) <= depth)).any(axis=1)

    def cut(self, v: np.ndarray, t: np.ndarray, margin: float, edge: float = 3e-3) -> tuple[np.ndarray, np.ndarray]:
        """A mesh (vertices, triangles) less what lies within `margin` of a taxel cell: triangles
        across that boundary (their corners, edge midpoints and centroid not all on one side) are
        split 1 to 4 until shorter than `edge` (CAD meshes carry slivers 100 mm long: dropped
        whole, one would leave a strip of the link bare), then those whose centroid is near go."""
        from trimesh.remesh import subdivide

        for _ in range(8):
            tri = v[t]
            probe = np.concatenate([tri, 0.5 * (tri + np.roll(tri, 1, axis=1)), tri.mean(axis=1, keepdims=True)], axis=1)
            near = self.near(probe.reshape(-1, 3), margin).reshape(len(t), 7)
            long = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1) > edge
            split = np.flatnonzero((near.any(axis=1) != near.all(axis=1)) & long)
            if not len(split):
                break
            v, t = subdivide(v, t, face_index=split)
        return v, t[~self.near(v[t].mean(axis=1), margin)]

    def guard(self, lift: float = 2e-3) -> np.ndarray:
        """Points no piece may come near: each cell's centre and corners on the skin and `lift` above it."""
        x, y, z = (self.frames[:, :, i] * h for i, h in ((0, self.half[:, None]), (1, self.half[:, None]), (2, 1.0)))
        cell = [self.positions + sx * x + sy * y for sx, sy in ((0, 0), (-1, -1), (-1, 1), (1, -1), (1, 1))]
        return np.concatenate(cell + [c + lift * z for c in cell])


def _collides(model, g) -> bool:
    return bool(model.geom_contype[g] or model.geom_conaffinity[g])


def point_clearance(spec: mujoco.MjSpec, points: dict[str, np.ndarray], q=None) -> dict[str, np.ndarray]:
    """Body name -> (n,) signed distance (m) of points (body frame) to the contact surface of that
    body: the smallest `mj_geomDistance` to the colliding geoms of the body and the bodies welded
    to it (negative: buried inside one, by at least that much); infinite where it has none."""
    s = spec.copy()
    probe = s.worldbody.add_body(name=PROBE, mocap=True)
    probe.add_geom(name=PROBE, type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[1e-6, 0, 0], contype=0, conaffinity=0)
    model = s.compile()
    data = mujoco.MjData(model)
    if q is not None:
        data.qpos[:len(q)] = q
    mujoco.mj_kinematics(model, data)
    pg = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, PROBE)
    fromto = np.zeros(6)
    out = {}
    for name, local in points.items():
        bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        weld = model.body_weldid[bid]
        geoms = np.array([g for g in range(model.ngeom) if g != pg and _collides(model, g)
                          and model.body_weldid[model.geom_bodyid[g]] == weld], int)
        world = np.asarray(local, float).reshape(-1, 3) @ data.xmat[bid].reshape(3, 3).T + data.xpos[bid]
        d = out[name] = np.full(len(world), np.inf)
        # a point is no nearer a geom than to its bounding sphere (inside it too: the depth is at most
        # the sphere's): geoms nearest first, stopping where that bound passes the best distance
        r = np.where(model.geom_rbound[geoms] > 0, model.geom_rbound[geoms], np.inf)  # 0: a plane, unbounded
        bound = np.linalg.norm(world[:, None] - data.geom_xpos[geoms][None], axis=2) - r[None]
        for i, p in enumerate(world):
            data.geom_xpos[pg] = p  # mj_geomDistance reads the pose from here: no kinematics per point
            for k in np.argsort(bound[i]):
                if bound[i, k] > min(d[i], 0.2):
                    break
                d[i] = min(d[i], mujoco.mj_geomDistance(model, data, int(geoms[k]), pg, 0.2, fromto))
    return out


def taxel_clearance(spec: mujoco.MjSpec, design: SkinDesign, q=None) -> np.ndarray:
    """(N,) signed distance (m) of each taxel to the contact surface of its link (`point_clearance`)."""
    t = design.taxels
    gaps = point_clearance(spec, {b: t.positions[t.body == bi] for bi, b in enumerate(design.bodies)}, q)
    out = np.full(len(t), np.inf)
    for bi, b in enumerate(design.bodies):
        out[t.body == bi] = gaps[b]
    return out


def fit_to_skin(spec: mujoco.MjSpec, design: SkinDesign | None, tol: float = 1e-3, shell_depth: float = 0.003) -> dict:
    """Edit `spec` so every link collides at its surface and every taxel is within `tol` of the
    contact surface (see the module doc; `design=None`: the robot alone). Returns {"pieces": count,
    "shrunk": geom names, "disabled": geom names, "shells": count}."""
    report = {"pieces": 0, "shrunk": [], "disabled": [], "shells": 0}
    for k, g in enumerate(spec.geoms):  # unnamed geoms (URDF primitives) get names to be edited by
        if not g.name:
            g.name = f"{g.parent.name}_geom{k}"
    _add_surface_pieces(spec, spec.compile(), design, report)
    if design is None or not len(design.taxels):
        return report
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
    surface |= {g for g in range(model.ngeom) if model.geom(g).name.startswith(PIECE_PREFIX)}
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


_PIECES: dict[str, list] = {}  # content digest -> pieces (scenes of one robot are built many times)
PIECES_VERSION = 7  # part of every digest: bump it when the way pieces are cut changes


def _add_surface_pieces(spec, model, design: SkinDesign | None, report: dict) -> None:
    """Every body that has a visual mesh and collides through other geoms collides through
    `surface_pieces` of its exposed visual surface instead; on a skinned link the pieces keep out
    of its taxel cells (`Footprint`), which its skin's shells cover (steps 2-4). Pieces are kept by
    a digest of what they depend on, in this process and on disk (`cache_dir`)."""
    MESH = mujoco.mjtGeom.mjGEOM_MESH
    visual = [g for g in range(model.ngeom) if model.geom_bodyid[g] and model.geom_type[g] == MESH
              and not _collides(model, g)]
    todo = [b for b in range(1, model.nbody) if any(model.geom_bodyid[g] == b for g in visual)
            and any(_collides(model, g) for g in np.flatnonzero(model.geom_bodyid == b))]
    if not todo:
        return
    q = model.key_qpos[0] if model.nkey else model.qpos0
    robot_key = geom_digest(model, [], _robot_digest(model, q), PIECES_VERSION, PIECE_TOL, PIECE_DEPTH, PIECE_BUDGET,
                        PIECE_MIN_SIZE, FOOTPRINT_MARGIN, GUARD_GAP)
    for b in todo:
        name = model.body(b).name
        cells = Footprint.of(design, name) if design is not None else None
        key = geom_digest(model, [], robot_key, name, *((cells.positions, cells.frames, cells.half) if cells else ()))
        if key not in _PIECES:
            pieces = load_pieces(key)
            if pieces is None:
                surf, outer, normals = _outer_surface(model, name, q)
                pieces = surface_pieces(surf, outer=(outer, normals), footprint=cells)
                save_pieces(key, pieces)
            _PIECES[key] = pieces
            if len(_PIECES) > 64:
                _PIECES.pop(next(iter(_PIECES)))
        for k, pts in enumerate(_PIECES[key]):
            mesh = spec.add_mesh(name=f"{PIECE_PREFIX}{name}_{k}")
            mesh.uservert = pts.ravel().tolist()
            spec.body(name).add_geom(name=mesh.name, type=MESH, meshname=mesh.name, group=SHELL_GROUP, density=0,
                                     contype=1, conaffinity=1, rgba=[0.5, 0.5, 0.6, 0.3])
        report["pieces"] += len(_PIECES[key])
        for g in np.flatnonzero(model.geom_bodyid == b):
            if _collides(model, g):
                sg = spec.geom(model.geom(g).name)
                sg.contype, sg.conaffinity, sg.group = 0, 0, 5  # kept for its mass, hidden, no contacts
                report["disabled"].append(sg.name)


def _robot_digest(model, q) -> str:
    """A digest of what a robot's surfaces at configuration q depend on: its visual meshes and
    their poses, the bodies' poses and joints."""
    visual = [g for g in range(model.ngeom) if model.geom_bodyid[g] and not _collides(model, g)]
    return geom_digest(model, visual, q, model.body_pos, model.body_quat, model.jnt_pos, model.jnt_axis,
                   model.jnt_bodyid.astype(float))


_MEMO: dict[str, object] = {}  # in this process: world triangles and outer faces by content digest


def _memo(key: str, make):
    if key not in _MEMO:
        _MEMO[key] = make()
        if len(_MEMO) > 128:
            _MEMO.pop(next(iter(_MEMO)))
    return _MEMO[key]


def _world_triangles(model, q) -> dict[str, np.ndarray]:
    """Body name -> its visual surface's triangles (k,3,3) in the world at configuration q."""
    def make():
        data = mujoco.MjData(model)
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        out = {}
        for b in range(1, model.nbody):
            if any(model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH and not _collides(model, g)
                   for g in np.flatnonzero(model.geom_bodyid == b)):
                surf = body_surface(model, model.body(b).name, budget=5000)
                out[model.body(b).name] = surf.vertices[surf.triangles] @ data.xmat[b].reshape(3, 3).T + data.xpos[b]
        return out

    return _memo("world" + _robot_digest(model, q), make)


def _outer_surface(model, name: str, q) -> tuple[Surface, np.ndarray, np.ndarray]:
    """A body's visual surface at full resolution and which of its triangles face the outside of
    the whole robot at configuration q, with their outward normals (`outer_faces`, the other
    links around it)."""
    def make():
        b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        surf = body_surface(model, name, budget=10 ** 9)
        return (surf, *outer_faces(surf, _in_frame(model, q, b, _world_triangles(model, q), exclude=name)))

    return _memo("outer" + _robot_digest(model, q) + name, make)


def _in_frame(model, q, b: int, world: dict, exclude: str) -> np.ndarray:
    """The other bodies' triangles (k,3,3) in body b's frame at configuration q."""
    data = mujoco.MjData(model)
    data.qpos[:] = q
    mujoco.mj_kinematics(model, data)
    tri = [t for name, t in world.items() if name != exclude]
    if not tri:
        return np.zeros((0, 3, 3))
    return (np.concatenate(tri) - data.xpos[b]) @ data.xmat[b].reshape(3, 3)


def exposed_triangles(model: mujoco.MjModel, q=None) -> dict[str, np.ndarray]:
    """Body name -> the triangles (k,3,3, body frame) of its visual surface that face the outside
    of the whole robot at configuration q (default: the first keyframe): `outer_faces` with the
    other links around it, as the surface pieces are cut (parts nested in a neighbour's housing
    and hidden walls are left out)."""
    q = (model.key_qpos[0] if model.nkey else model.qpos0) if q is None else q
    out = {}
    for name in _world_triangles(model, q):
        surf, outer, _ = _outer_surface(model, name, q)
        out[name] = surf.vertices[surf.triangles[outer]]
    return out


def geom_digest(model, geoms, *values) -> str:
    import hashlib

    h = hashlib.sha1()
    for g in geoms:
        h.update(np.concatenate([model.geom_pos[g], model.geom_quat[g], model.geom_size[g]]).tobytes())
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
            h.update(mesh_vertices(model, g).tobytes())
    for x in values:
        h.update(x.encode() if isinstance(x, str) else np.asarray(x, float).tobytes())
    return h.hexdigest()


def _triangle_points(tri: np.ndarray, spacing: float) -> np.ndarray:
    """Points on every triangle (k,3,3) of a mesh, no farther than `spacing` apart along an edge."""
    edge = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)
    steps = np.clip(np.ceil(edge / spacing), 1, 200).astype(int)
    out = []
    for k in np.unique(steps):
        sel = tri[steps == k]
        i, j = np.meshgrid(np.arange(k + 1), np.arange(k + 1), indexing="ij")
        keep = (i + j) <= k
        u, w = i[keep] / k, j[keep] / k
        out.append((sel[:, None, 0] + u[None, :, None] * (sel[:, None, 1] - sel[:, None, 0])
                    + w[None, :, None] * (sel[:, None, 2] - sel[:, None, 0])).reshape(-1, 3))
    return np.concatenate(out) if out else np.zeros((0, 3))


def outer_faces(surf: Surface, around: np.ndarray | None = None, pitch: float = VOXEL) -> tuple[np.ndarray, np.ndarray]:
    """Which triangles of a surface face the outside, and their outward unit normals. The surface
    and `around` (triangles (k,3,3) of the robot's other links in this link's frame: they close
    the link's open ends) are voxelised (`pitch`), the space outside them flood-filled from the
    border of the link's box, and a triangle is outer where a point `1.5 pitch` off its centroid,
    on either side, is outside. A CAD housing's inner walls, hidden parts and wrongly wound
    triangles are told apart this way (the Gen3's links are 2-3 mm walls around hollow insides)."""
    from scipy import ndimage

    v, t = surf.vertices, surf.triangles
    lo = v.min(axis=0) - 3 * pitch
    hi = v.max(axis=0) + 3 * pitch
    shape = np.ceil((hi - lo) / pitch).astype(int) + 1
    pts = [_triangle_points(v[t], 0.5 * pitch)]
    if around is not None and len(around):
        near = around[((around.max(axis=1) > lo) & (around.min(axis=1) < hi)).all(axis=1)]
        p = _triangle_points(near, 0.5 * pitch)
        pts.append(p[((p > lo) & (p < hi)).all(axis=1)])
    idx = np.floor((np.concatenate(pts) - lo) / pitch).astype(int)
    wall = np.zeros(shape, bool)
    wall[tuple(np.clip(idx, 0, shape - 1).T)] = True
    wall = ndimage.binary_dilation(wall)  # closes cracks narrower than a voxel between CAD parts
    wall[[0, -1]], wall[:, [0, -1]], wall[:, :, [0, -1]] = False, False, False  # the box's border is outside
    labels, _ = ndimage.label(~wall)
    outside = labels == labels[0, 0, 0]
    n = surf.face_normals
    cen = v[t].mean(axis=1)

    def out_at(q):
        return outside[tuple(np.clip(np.floor((q - lo) / pitch).astype(int), 0, shape - 1).T)]

    front, back = out_at(cen + 1.5 * pitch * n), out_at(cen - 1.5 * pitch * n)
    return front | back, np.where((front | ~back)[:, None], n, -n)


def surface_pieces(surf: Surface, tol: float = PIECE_TOL, depth: float = PIECE_DEPTH, budget: int = PIECE_BUDGET,
                   around: np.ndarray | None = None, min_size: float = PIECE_MIN_SIZE,
                   footprint: Footprint | None = None, outer: tuple | None = None) -> list[np.ndarray]:
    """Convex pieces (point sets) that make a collision model at the surface. The outer triangles
    (`outer_faces`, or `outer` given as its result; wound outward; `around`: the robot's other
    links) are decimated to `budget` (on a skinned link, then cut `FOOTPRINT_MARGIN` clear of its
    taxel cells, `Footprint.cut`) and cut into 32 patches, each patch with the same corners `depth`
    under it one piece; a piece that buries an outer point more than `tol` is made thinner (the
    slab may cross a wall thinner than itself) down to `MIN_PIECE_DEPTH`, then split in two along
    its longest spread (recursively), until none does or it spans less than `min_size` (a bound on
    the pieces of fine CAD detail). A piece within `GUARD_GAP` of a taxel cell or the space just
    above it is split, and left out when it is one triangle: no piece stands above the skin
    (probes would meet it before the skin)."""
    import trimesh

    from skinsafe.core.robot.meshes import decimate

    outer, normals = outer_faces(surf, around) if outer is None else outer
    t = surf.triangles[outer]
    flip = np.einsum("ij,ij->i", surf.face_normals[outer], normals[outer]) < 0
    t[flip] = t[flip][:, ::-1]
    small = decimate(trimesh.Trimesh(surf.vertices, t, process=True), budget)
    v, t = np.asarray(small.vertices, float), np.asarray(small.faces, np.int64)
    guard = None
    if footprint is not None:  # the skin's cells and a margin are left to its shells
        v, t = footprint.cut(v, t, FOOTPRINT_MARGIN)
        guard = _Cloud(footprint.guard())
    if not len(t):
        return []
    n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    t, n = t[np.linalg.norm(n, axis=1) > 0], n[np.linalg.norm(n, axis=1) > 0]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    cen = v[t].mean(axis=1)
    check = _Cloud(np.vstack([v, np.unique(_triangle_points(v[t], 0.004).round(6), axis=0)]))  # inside a triangle too
    def halves(faces):
        x = cen[faces] - cen[faces].mean(axis=0)
        low = x @ np.linalg.svd(x, full_matrices=False)[2][0] <= 0
        if low.all() or not low.any():
            low = np.arange(len(faces)) < len(faces) // 2
        return [faces[low], faces[~low]]

    stack = [np.arange(len(t))]
    for _ in range(5):  # a link is rarely convex: start from 32 patches (8 took 1.3-2.5x as long for the same pieces)
        stack = [h for f in stack for h in (halves(f) if len(f) > 1 else [f])]
    stack = [(f, depth) for f in stack]
    pieces = []
    while stack:
        faces, d = stack.pop()
        if not len(faces):
            continue
        corners = v[t[faces]]
        pts = np.concatenate([corners, corners - d * n[faces, None, :]]).reshape(-1, 3)
        hull = _Hull(pts)
        if guard is not None and hull.buries(guard, -GUARD_GAP):  # near the skin: smaller, or none
            stack += [(h, depth) for h in halves(faces)] if len(faces) > 1 else []
        elif np.ptp(corners.reshape(-1, 3), axis=0).max() < min_size or not hull.buries(check, tol):
            pieces.append(np.unique(pts.round(9), axis=0))
        elif d > MIN_PIECE_DEPTH:  # thinner first: the slab may cross a wall thinner than itself
            stack.append((faces, d / 2))
        elif len(faces) > 1:  # then smaller: the patch is not convex enough
            stack += [(h, depth) for h in halves(faces)]
        else:
            pieces.append(np.unique(pts.round(9), axis=0))
    return pieces


class _Cloud:
    """Points with a k-d tree, to find those near a piece quickly."""

    def __init__(self, points: np.ndarray):
        from scipy.spatial import cKDTree

        self.points, self.tree = points, cKDTree(points)


class _Hull:
    """The convex hull of a piece's points, its face planes computed once, when first needed."""

    def __init__(self, pts: np.ndarray):
        self.pts, self.lo, self.hi, self._eq = pts, pts.min(axis=0), pts.max(axis=0), None

    def buries(self, check: _Cloud, tol: float, chunk: int = 1024) -> bool:
        """Whether any `check` point lies more than `tol` inside the hull (a negative `tol`: less than
        -tol outside it; checked in strided chunks: a piece that buries points is usually told by the first)."""
        from scipy.spatial import QhullError

        lo, hi = self.lo + tol, self.hi - tol
        if (lo >= hi).any():
            return False
        near = check.points[check.tree.query_ball_point((lo + hi) / 2, np.linalg.norm(hi - lo) / 2 + 1e-9)]
        near = near[((near > lo) & (near < hi)).all(axis=1)]
        if not len(near):
            return False
        if self._eq is None:
            try:
                self._eq = ConvexHull(self.pts).equations
            except QhullError:
                self._eq = np.zeros((0, 4))
        if not len(self._eq):
            return False
        eq = self._eq
        stride = max(1, len(near) // chunk)
        return any(((near[k::stride] @ eq[:, :3].T + eq[:, 3]).max(axis=1) < -tol).any() for k in range(stride))


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
    taxel cells' corners and the same points `depth` below them (body frame). A block that buries
    a taxel more than 0.2 mm (its own over a hollow, another module's where the link folds) becomes
    one shell per cell, and a cell that still does is made thinner (halved, down to 0.5 mm).
    Returns the count."""
    t = design.taxels
    idx = np.flatnonzero(t.module == module.id)
    k = np.arange(len(idx))
    cols = max(module.cols, 1)
    piece = (k // cols) // block * (cols // block + 1) + (k % cols) // block
    h = module.pitch / 2
    mine = t.positions[idx]
    reach = np.linalg.norm(mine - mine.mean(axis=0), axis=1).max() + 2 * h + depth
    same = np.flatnonzero((t.body == t.body[idx[0]]) & (t.module != module.id))
    others = t.positions[same][np.linalg.norm(t.positions[same] - mine.mean(axis=0), axis=1) < reach]
    count = 0

    def shell(sel, d):
        p, f = t.positions[sel], t.frames[sel]
        corners = [p + sx * h * f[:, :, 0] + sy * h * f[:, :, 1] for sx in (-1, 1) for sy in (-1, 1)]
        top = np.concatenate([p] + corners)
        return np.concatenate([top, top - d * np.concatenate([f[:, :, 2]] * 5)])

    def buries(pts, p) -> bool:
        if not len(p):
            return False
        eq = ConvexHull(pts).equations
        return bool((-(p @ eq[:, :3].T + eq[:, 3]).max(axis=1)).max() > 2e-4)

    pieces = []
    for j in np.unique(piece):
        sel = idx[piece == j]
        pts = shell(sel, depth)
        if not buries(pts, np.concatenate([t.positions[sel], others])):
            pieces.append(pts)
            continue
        for i in sel:
            d = depth
            while buries(pts := shell([i], d), others) and d > 0.5e-3:
                d /= 2
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

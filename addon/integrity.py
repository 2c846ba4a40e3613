"""Every edit of Blender's Object menu and outliner keeps the skin true, not only the listed ones.

The robot's links are the robot's (`links`): a link deleted is put back (its object survives, held by
`scene.skinsafe.links`, its children still on it), re-parented or moved is put back on its parent at the
pose, one whose mesh changed (transforms or modifiers applied, origin set) or that was converted gets its mesh
or object again from the robot description.

Each module object is one whole FPC of the design (`modules`): its parent and transform are normalised keeping
where it is (parented to another link, it moves onto that link); a mesh whose data changed while its pads stay
where the design has them (transforms applied, origin set, modifiers applied) is rebuilt from the design at its
placement; a separated piece is put back; a converted object is made a module again; a curve module whose outline
curve was joined, converted or deleted gets it again from the design. A module joined into another object (a
module, a robot link, any mesh) is split back out of it (`joined`, before the links are put back). Each returns
what it did, a line each, for the panel."""
import warnings
from types import SimpleNamespace

import bmesh
import bpy
import mujoco
import numpy as np
from scipy.spatial import cKDTree

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import core_to_blender as c2b
from skinsafe.addon import designer
from skinsafe.core.design.placement import placed_from_design
from skinsafe.core.skin.ids import IdRuleWarning
from skinsafe.core.skin.model import DesignError

PAD_TOL = 5e-4  # m: a pad within this of its design place has not moved
JOIN_TOL = 1e-5  # m: a joined pad's corners keep their place to float32 rounding (a mesh near it is not one)


def _same_key(a, b) -> bool:
    return b2c.close(a, b, 1e-6 + 1e-5 * max(map(abs, b)))


def adopt_links(scene) -> None:
    """A file saved before the links were kept: keep the robot's collection's objects as its links."""
    for body, obj in b2c.body_objects(scene).items():
        it = scene.skinsafe.links.add()
        it.body, it.object = body, obj
        it.mesh_key = b2c.mesh_key(obj.data) if obj.type == "MESH" else (0.0,) * 5


def links(scene) -> tuple[list[str], set[str]]:
    """Put every robot link back as the robot description and the pose have it: what was put back, in words,
    and the bodies whose objects were (an edit of a link, e.g. transforms applied, also moves its children)."""
    s = scene.skinsafe
    if not len(s.links):
        adopt_links(scene)
    robot = b2c.robot_for(scene)
    m = robot.model
    coll = bpy.data.collections.get(b2c.COLLECTION)
    if coll is None:
        coll = bpy.data.collections.new(b2c.COLLECTION)
        scene.collection.children.link(coll)
    said, objs, touched = [], {}, set()
    for it in s.links:
        n = len(said)
        b, o = m.body(it.body).id, it.object
        if o is None or (o.type != "MESH") != (b == 0):  # purged, or converted to another type: made again
            new = c2b.link_object(m, b, robot.name)
            coll.objects.link(new)
            if o is not None:
                for child in o.children:
                    child.parent = new
                bpy.data.objects.remove(o, do_unlink=True)
            it.object, o = new, new
            it.mesh_key = b2c.mesh_key(o.data) if b else (0.0,) * 5
            said.append(f"robot link '{it.body}' was converted or removed: made again from the robot description")
        elif o.name not in scene.objects:
            coll.objects.link(o)
            said.append(f"robot link '{it.body}' cannot be deleted (the robot's links are the robot's): put back")
        if b and not _same_key(b2c.mesh_key(o.data), it.mesh_key):
            old, o.data = o.data, c2b.link_mesh(m, it.body)
            if old.users == 0:
                bpy.data.meshes.remove(old)
            it.mesh_key = b2c.mesh_key(o.data)
            said.append(f"robot link '{it.body}': its mesh is the robot description's (transforms, origin or modifiers "
                        "applied to it are undone)")
        objs[b] = o
        if len(said) > n:
            touched.add(it.body)
    d = mujoco.MjData(m)
    d.qpos[:] = b2c.pose(scene)
    mujoco.mj_kinematics(m, d)
    R, par = d.xmat.reshape(-1, 3, 3), m.body_parentid
    local = np.zeros((m.nbody, 4, 4))  # each body in its parent's frame (the root's parent is itself: identity)
    local[:, :3, :3] = np.einsum("nji,njk->nik", R[par], R)  # rigid inverses by transposes: no LAPACK call per
    local[:, :3, 3] = np.einsum("nji,nj->ni", R[par], d.xpos - d.xpos[par])  # link (its threads stall under load)
    local[:, 3, 3] = 1.0
    moved = []
    for b, o in objs.items():
        parent = objs.get(int(par[b])) if b else None
        W = local[b]
        ident = b2c.close(np.array(o.matrix_parent_inverse), np.eye(4), 1e-6)
        if o.parent is not parent or not ident or not b2c.close(np.array(o.matrix_basis), W, 1e-5):
            o.parent = parent
            o.matrix_parent_inverse.identity()
            o.matrix_basis = b2c.to_matrix(W)
            moved.append(m.body(b).name)
    if moved:
        said.append(f"robot links {', '.join(moved)} are posed by the robot's joints (Skin > Robot): put back")
    return said, touched | set(moved)


def converted_ids(scene) -> str:
    """A file saved under an older taxel-id rule: its design stored with the stable ids (`ids.converted`, through
    the taxel map's reader), and what changed, in words ("" where nothing did)."""
    b2c.clear_caches()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", IdRuleWarning)
        design = b2c.design_of(scene)
    said = [str(w.message) for w in caught if issubclass(w.category, IdRuleWarning)]
    if design is None or not said:
        return ""
    c2b.store_design(scene, design)
    return f"this file was saved under an older taxel-id rule, converted on load: {said[0]}"


def _centres(obj) -> np.ndarray | None:
    """World hexagon centres of a module object's mesh (None: not a mesh of hexagons)."""
    me = obj.data
    if len(me.vertices) % 6 or len(me.polygons) * 6 != len(me.vertices):
        return None
    return c2b.module_taxel_centres(obj)


def _design_world(scene, design, mid: int) -> np.ndarray:
    t = design.taxels
    m = next(m for m in design.modules if m.id == mid)
    W = np.array(b2c.body_objects(scene)[m.body].matrix_world)
    return t.positions[t.module == mid] @ W[:3, :3].T + W[:3, 3]


def _within(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether every point of `a` is one of `b`'s (within PAD_TOL)."""
    return bool(len(a)) and len(b) and float(cKDTree(b).query(a)[0].max()) < PAD_TOL


def rebuild(obj, design, mid: int) -> None:
    """Make a module object's mesh from its design taxels again, at its last placement."""
    obj.matrix_basis = b2c.to_matrix(np.array(obj.skinsafe_module.placed_matrix).reshape(4, 4))
    p = placed_from_design(design, mid)
    c2b.module_mesh(obj, p.positions, p.frames, p.module.taxel_diameter)


def remake(scene, design, mid: int) -> bpy.types.Object:
    """A module object for design module `mid` (its object joined into another or converted): its settings from
    the module, its frame from the placement record (anchor, rows, the nearest taxel's normal)."""
    m = next(m for m in design.modules if m.id == mid)
    p = placed_from_design(design, mid)
    rec = m.placement if isinstance(m.placement, dict) else {}
    t = design.taxels
    on = np.flatnonzero(t.module == mid)
    origin = np.asarray(rec.get("anchor", t.positions[on].mean(axis=0)), float)
    z = t.frames[on[np.argmin(np.linalg.norm(t.positions[on] - origin, axis=1))], :, 2]
    x = np.asarray(rec.get("direction", t.frames[on[0], :, 0]), float)
    x = x - (x @ z) * z
    x /= np.linalg.norm(x)
    p.origin, p.origin_frame = origin, np.stack([x, np.cross(z, x), z], axis=1)
    settings = SimpleNamespace(**{k: getattr(m, k) for k in (
        "template", "rows", "cols", "pitch", "taxel_diameter", "margin", "min_bend_radius", "max_strain")},
        method=rec.get("method", "geodesic"), mirrored=bool(rec.get("mirrored")), outline=None)  # the template's fields
    return c2b.new_module_object(scene, b2c.body_objects(scene)[m.body], m, p, settings)


def _corners(scene, design, mid: int) -> np.ndarray:
    """World corners of a design module's pads, as its object's mesh has them (`module_mesh`)."""
    p = placed_from_design(design, mid)
    W = np.array(b2c.body_objects(scene)[p.module.body].matrix_world)
    return c2b.pad_corners(p.positions, p.frames, p.module.taxel_diameter) @ W[:3, :3].T + W[:3, 3]


def joined(scene) -> list[str]:
    """Split back every module whose object is gone while its pads are in another mesh object (Ctrl+J with another
    module, a robot link or any mesh active): the module gets its object again and its pads leave that object (a
    link's mesh is put back whole by `links`, a module's made from the design by `modules`). Only objects whose
    mesh changed are searched, so a copy left in place keeps its pads; what was done."""
    design = b2c.design_of(scene)
    if design is None:
        return []
    present = {o.skinsafe_module.module_id for o in b2c.module_objects(scene)}
    corners = {m.id: _corners(scene, design, m.id) for m in design.modules if m.id not in present}
    if not corners:
        return []
    link_keys = {it.object.as_pointer(): tuple(it.mesh_key) for it in scene.skinsafe.links if it.object is not None}
    said = []
    for o in [o for o in scene.objects if o.type == "MESH" and o.mode != "EDIT" and len(o.data.vertices)]:
        key = tuple(o.skinsafe_module.mesh_key) if o.skinsafe_module.is_module else link_keys.get(o.as_pointer())
        if key is not None and _same_key(b2c.mesh_key(o.data), key):
            continue
        co = np.empty(len(o.data.vertices) * 3)
        o.data.vertices.foreach_get("co", co)
        W = np.array(o.matrix_world)
        tree = cKDTree(co.reshape(-1, 3) @ W[:3, :3].T + W[:3, 3])
        for mid in list(corners):
            dist, at = tree.query(corners[mid])
            if dist.max() >= JOIN_TOL:
                continue
            del corners[mid]
            name = remake(scene, design, mid).name
            said.append(f"module '{name}' was joined into '{o.name}': a module is one FPC, split back")
            if key is None:  # neither a module nor a link: the pads cut out of it
                bm = bmesh.new()
                bm.from_mesh(o.data)
                bm.verts.ensure_lookup_table()
                bmesh.ops.delete(bm, geom=[bm.verts[i] for i in np.unique(at)], context="VERTS")
                bm.to_mesh(o.data)
                bm.free()
    return said


def _outline(scene, obj, design) -> str:
    """A curve module whose outline curve is gone (joined into another curve, deleted), is no curve (converted) or
    holds more than its one closed spline (another curve joined into it): a curve object made again from the
    design's outline (its placement record), so the module re-generates as designed; what was done ("": none)."""
    st = obj.skinsafe_module.settings
    cu = st.outline
    if st.template != "curve" or (cu is not None and scene.objects.get(cu.name) is cu and cu.type == "CURVE"
                                  and len(cu.data.splines) == 1):
        return ""
    rec = next(m for m in design.modules if m.id == obj.skinsafe_module.module_id).placement
    if "outline" not in rec:
        return ""
    pts = np.asarray(rec["outline"], float)
    for c in [c for c in scene.objects if c.type == "CURVE" and len(c.data.splines) == 1]:  # still there: taken
        if (got := b2c.outline_of(SimpleNamespace(template="curve", outline=c, mirrored=st.mirrored))).shape == \
                pts.shape and b2c.close(got.ravel(), pts.ravel(), 1e-7):
            st.outline = c
            return ""
    data = bpy.data.curves.new(f"{obj.name} outline", "CURVE")
    sp = data.splines.new("POLY")
    pts = pts * ((-1.0 if st.mirrored else 1.0), 1.0)  # the record's is mirrored
    sp.points.add(len(pts) - 1)
    for p, (x, y) in zip(sp.points, pts):
        p.co = (x, y, 0.0, 1.0)
    sp.use_cyclic_u = True
    new = bpy.data.objects.new(data.name, data)
    obj.users_collection[0].objects.link(new)
    st.outline = new
    return (f"module '{obj.name}': its outline curve was joined, converted or deleted; made again from the design "
            f"('{new.name}')")


def modules(scene, kept: set[str] = frozenset()) -> list[str]:
    """Make every module object one whole FPC of the design again after an edit of its object or data; what
    was done. The modules on the links in `kept` (just put back by `links`) go back to their placements: an edit of
    their link moved them with it. Objects in Edit Mode wait for its end."""
    design = b2c.design_of(scene)
    if design is None:
        return []
    bodies = b2c.body_objects(scene)
    body_of = {o.as_pointer(): b for b, o in bodies.items()}
    known = {m.id for m in design.modules}
    said = []
    for o in [o for o in b2c.module_objects(scene) if o.type != "MESH" and o.mode != "EDIT"]:
        mid, name = o.skinsafe_module.module_id, o.name
        bpy.data.objects.remove(o, do_unlink=True)
        if mid in known and not any(x.skinsafe_module.module_id == mid for x in b2c.module_objects(scene)):
            remake(scene, design, mid).name = name
            said.append(f"module '{name}' was converted: a module is its FPC's pads, made again from the design")
    for o in [o for o in b2c.module_objects(scene) if o.mode != "EDIT"]:
        mm = o.skinsafe_module
        pb = body_of.get(o.parent.as_pointer()) if o.parent is not None else None
        if pb is not None and pb != mm.body and mm.body in bodies:
            said.append(_move_to(scene, o, pb, bodies))
        if mm.body in kept and mm.body in bodies:
            o.parent = bodies[mm.body]
            o.matrix_parent_inverse.identity()
            o.matrix_basis = b2c.to_matrix(np.array(mm.placed_matrix).reshape(4, 4))
        elif mm.body in bodies and o.parent is not bodies[mm.body]:
            _reattach(o, bodies[mm.body])
        elif mm.body in bodies:
            designer.attach(o, bodies[mm.body])
        if mm.module_id in known and (line := _outline(scene, o, design)):
            said.append(line)
        if mm.module_id not in known or _same_key(b2c.mesh_key(o.data), mm.mesh_key):
            continue
        centres, own = _centres(o), _design_world(scene, design, mm.module_id)
        if mm.owner != o.session_uid and centres is not None and len(centres) < len(own) and _within(centres, own):
            said.append(f"'{o.name}' was separated from module '{o.name.rsplit('.', 1)[0]}': a module is one FPC, its "
                        "pads were put back")
            bpy.data.objects.remove(o, do_unlink=True)
            continue
        if centres is None or len(centres) != len(own) or not _within(centres, own):
            said.append(f"module '{o.name}': its mesh is made from the design (its data was edited): made again")
        rebuild(o, design, mm.module_id)
    return said


def _reattach(obj, body_obj) -> None:
    """A module object whose parent was cleared or set to another object (not a link) goes back on its link: where
    its local transform still is its placement (a parent cleared without keeping the transform), there; else
    where it now is in the world."""
    if b2c.moved(obj):
        designer.attach(obj, body_obj)
        return
    obj.parent = body_obj
    obj.matrix_parent_inverse.identity()


def _move_to(scene, obj, body: str, bodies) -> str:
    """A module object parented to another link: re-placed on that link where it is, or put back on its own."""
    mm = obj.skinsafe_module
    old, placed = mm.body, list(mm.placed_matrix)
    mm.body = body
    try:
        designer.regenerate(scene, obj)
        return f"module '{obj.name}' moved from '{old}' to '{body}' (its new parent): re-placed there"
    except DesignError as e:
        mm.body, mm.error = old, ""
        obj.parent = bodies[old]
        obj.matrix_parent_inverse.identity()
        obj.matrix_basis = b2c.to_matrix(np.array(placed).reshape(4, 4))
        mm.placed_matrix = placed
        return (f"module '{obj.name}' parented to '{body}' does not lie on it ({e}); put back on '{old}': move it "
                f"onto '{body}' first")

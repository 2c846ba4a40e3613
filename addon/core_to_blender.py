"""core -> Blender: robot bodies as parented mesh objects, poses, module meshes (one hexagon per
taxel), heat-map colours and the design stored in the .blend as a text datablock."""
import json
import random
from dataclasses import replace

import bpy
import mujoco
import numpy as np

from skinsafe.addon.blender_to_core import (
    COLLECTION,
    TEXT_NAME,
    _designs,
    body_objects,
    design_of,
    matrix_key,
    pose,
    robot_for,
    to_matrix,
)
from skinsafe.addon.blender_to_core import mesh_key as b2c_mesh_key
from skinsafe.core.design.surface import body_surface
from skinsafe.core.skin import taxel_map
from skinsafe.core.skin.ids import with_stable_ids

# viridis at 0, .25, .5, .75, 1
_VIRIDIS = np.array([[0.267, 0.005, 0.329], [0.229, 0.322, 0.546], [0.128, 0.567, 0.551],
                     [0.369, 0.789, 0.383], [0.993, 0.906, 0.144]])


def srgb_to_linear(rgb: np.ndarray) -> np.ndarray:
    """sRGB colour components (0-1) as the linear values Blender's colours hold."""
    rgb = np.asarray(rgb, dtype=float)
    return np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)


def heat_colors(values: np.ndarray, vmax: float | None = None) -> np.ndarray:
    """RGBA (n,4) viridis colours of values scaled to [0, vmax], in linear RGB (what Blender's float
    colour attributes hold; the sRGB view transform shows them as the viridis map)."""
    v = np.asarray(values, dtype=float)
    top = vmax if vmax else (float(v.max()) if v.size and v.max() > 0 else 1.0)
    s = np.clip(v / top, 0, 1) * (len(_VIRIDIS) - 1)
    i = np.minimum(s.astype(int), len(_VIRIDIS) - 2)
    f = (s - i)[:, None]
    rgb = _VIRIDIS[i] * (1 - f) + _VIRIDIS[i + 1] * f
    rgb = srgb_to_linear(rgb)
    return np.concatenate([rgb, np.ones((len(v), 1))], axis=1)


def _mesh_from_arrays(name, verts, tris=None, polys=None, corner_normals=None):
    """A mesh from vertices and triangles (or equal-sized polygons (n,k)) through foreach_set."""
    faces = tris if tris is not None else polys
    me = bpy.data.meshes.new(name)
    k = faces.shape[1] if len(faces) else 3
    me.vertices.add(len(verts))
    me.vertices.foreach_set("co", np.asarray(verts, dtype=np.float32).ravel())
    me.loops.add(faces.size)
    me.loops.foreach_set("vertex_index", faces.astype(np.int32).ravel())
    me.polygons.add(len(faces))
    me.polygons.foreach_set("loop_start", (np.arange(len(faces)) * k).astype(np.int32))
    me.update()
    if corner_normals is not None:
        me.normals_split_custom_set(corner_normals.reshape(-1, 3).tolist())
    return me


def build_robot(scene, ref) -> bpy.types.Object:
    """Replace the scene's robot with `ref`: one mesh object per body (its geoms' surface in the
    body frame), parented as the kinematic tree, joint data as custom properties."""
    s = scene.skinsafe
    for it in s.links:  # a link deleted from the scene is still held here: it goes too
        if it.object is not None and it.object.name not in scene.objects:
            bpy.data.objects.remove(it.object, do_unlink=True)
    old = bpy.data.collections.get(COLLECTION)
    if old is not None:
        for o in list(old.objects):
            bpy.data.objects.remove(o, do_unlink=True)
        bpy.data.collections.remove(old)
    s.robot_kind, s.robot_name, s.robot_path = ref.kind, ref.name, ref.path or ""
    s.robot_package_dirs = ";".join(ref.package_dirs)
    s.robot_xacro_args = ";".join(f"{k}:={v}" for k, v in ref.xacro_args.items())
    robot = robot_for(scene)
    m = robot.model
    coll = bpy.data.collections.new(COLLECTION)
    scene.collection.children.link(coll)
    s.links.clear()
    objs = {}
    for b in range(m.nbody):
        obj = link_object(m, b, robot.name)
        coll.objects.link(obj)
        obj.parent = objs.get(int(m.body_parentid[b])) if b else None
        objs[b] = obj
        it = s.links.add()
        it.body, it.object = obj["skinsafe_body"], obj
        it.mesh_key = b2c_mesh_key(obj.data) if obj.data is not None else (0.0,) * 5
    root = objs[0]
    s.joints.clear()
    for j in range(m.njnt):
        if int(m.jnt_type[j]) in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            item = s.joints.add()
            item.name = m.joint(j).name
            lo, hi = (m.jnt_range[j] if m.jnt_limited[j] else (-np.pi, np.pi))
            item.lower, item.upper = float(lo), float(hi)
            item["value"] = float(robot.home[m.jnt_qposadr[j]])  # no update callback per joint
    clear_design(scene)
    apply_pose(scene)
    return root


def link_object(m, b: int, robot_name: str) -> bpy.types.Object:
    """Body `b` of model `m` as an object from the robot description: its geoms' surface in the body frame (an
    empty for the root), the joint's data as custom properties; not linked to a collection nor parented."""
    name = m.body(b).name
    if b == 0:
        obj = bpy.data.objects.new(f"robot {robot_name}", None)
        obj["skinsafe_robot"] = robot_name
    else:
        obj = bpy.data.objects.new(name, link_mesh(m, name))
    obj["skinsafe_body"] = name
    for j in range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b]) if m.body_jntnum[b] else ():
        jt = int(m.jnt_type[j])
        obj["joint_name"] = m.joint(j).name
        obj["joint_type"] = mujoco.mjtJoint(jt).name.removeprefix("mjJNT_").lower()
        obj["joint_axis"] = [float(a) for a in m.jnt_axis[j]]
        obj["joint_range"] = [float(a) for a in m.jnt_range[j]] if m.jnt_limited[j] else [-np.inf, np.inf]
    return obj


def link_mesh(m, name: str) -> bpy.types.Mesh:
    """A body's design surface as a mesh (empty for a body without geometry)."""
    try:
        surf = body_surface(m, name)
        return _mesh_from_arrays(name, surf.vertices, tris=surf.triangles, corner_normals=surf.corner_normals)
    except Exception:  # a body without geometry (DesignError) stays an empty mesh
        return bpy.data.meshes.new(name)


def apply_pose(scene) -> None:
    """Move every body object to the pose of the panel's joint values (MuJoCo forward kinematics)."""
    if not scene.skinsafe.robot_kind:
        return
    robot = robot_for(scene)
    m = robot.model
    d = mujoco.MjData(m)
    d.qpos[:] = pose(scene)
    mujoco.mj_kinematics(m, d)
    world = np.zeros((m.nbody, 4, 4))
    world[:, 3, 3] = 1
    world[:, :3, :3] = d.xmat.reshape(-1, 3, 3)
    world[:, :3, 3] = d.xpos
    for name, obj in body_objects(scene).items():
        b = m.body(name).id
        local = np.linalg.inv(world[m.body_parentid[b]]) @ world[b] if b else world[0]
        obj.matrix_parent_inverse.identity()
        obj.matrix_basis = to_matrix(local)


def pad_corners(positions, frames, diameter: float) -> np.ndarray:
    """(N x 6, 3) corners of the hexagon pads a module object shows for its taxels (in their frame), 0.1 mm above."""
    ang = np.arange(6) * np.pi / 3
    ring = (np.cos(ang)[None, :, None] * frames[:, None, :, 0] + np.sin(ang)[None, :, None] * frames[:, None, :, 1])
    return (positions[:, None, :] + 0.5 * diameter * ring + 1e-4 * frames[:, None, :, 2]).reshape(-1, 3)


def module_mesh(obj, positions, frames, diameter: float) -> None:
    """Show a module's taxels (body frame) as hexagons of the taxel diameter in `obj`'s frame."""
    Minv = np.linalg.inv(np.array(obj.matrix_basis))
    local = pad_corners(positions, frames, diameter) @ Minv[:3, :3].T + Minv[:3, 3]
    old = obj.data
    me = _mesh_from_arrays(old.name, local, polys=np.arange(len(local)).reshape(-1, 6))
    me.attributes.new("retractability", "FLOAT", "FACE")
    me.color_attributes.new("heat", "FLOAT_COLOR", "CORNER")
    obj.data = me
    if old.users == 0:
        bpy.data.meshes.remove(old)
    module_mesh_key(obj)


def module_taxel_centres(obj) -> np.ndarray:
    """The taxel centres of a module object in world coordinates (hexagon centres)."""
    me = obj.data
    co = np.empty(len(me.vertices) * 3)
    me.vertices.foreach_get("co", co)
    local = co.reshape(-1, 6, 3).mean(axis=1)
    W = np.array(obj.matrix_world)
    return local @ W[:3, :3].T + W[:3, 3]


def show_heat(scene, design, values: np.ndarray) -> None:
    """Write per-taxel values (design order) to each module mesh: a face attribute and colours."""
    t = design.taxels
    rgba = heat_colors(values)
    for obj in scene.objects:
        mm = obj.skinsafe_module
        if not mm.is_module:
            continue
        on = np.flatnonzero(t.module == mm.module_id)
        me = obj.data
        if len(me.polygons) != len(on):
            continue
        me.attributes["retractability"].data.foreach_set("value", values[on].astype(np.float32))
        me.color_attributes["heat"].data.foreach_set("color", np.repeat(rgba[on], 6, axis=0).astype(np.float32).ravel())
        me.color_attributes.active_color = me.color_attributes["heat"]
        me.update()


def store_design(scene, design):
    """Keep the design, its taxel ids made stable (module id and index), in the .blend (text datablock,
    taxel-map JSON) and in the session cache; returns what was stored. Its `retired_modules` keep the history:
    every id the scene's design had (or, with none stored, every id below `next_module_id`: all were given) that
    this one lacks, so boards and records never see an id come back meaning another module."""
    s, old = scene.skinsafe, design_of(scene)
    had = set(range(s.next_module_id)) if old is None else {m.id for m in old.modules} | set(old.retired_modules)
    design = replace(with_stable_ids(design), retired_modules=tuple(sorted(
        (had | set(design.retired_modules)) - {m.id for m in design.modules})))
    text = bpy.data.texts.get(TEXT_NAME) or bpy.data.texts.new(TEXT_NAME)
    # One value per line: Blender's text editor is quadratic in the length of a line.
    text.from_string(json.dumps(taxel_map.to_dict(design), indent=0, separators=(",", ":"), allow_nan=False))
    _new_rev(scene)
    _designs[scene.name] = (scene.skinsafe.design_rev, design)
    s.next_module_id = max(s.next_module_id, 1 + max([m.id for m in design.modules] + list(design.retired_modules),
                                                     default=-1))
    return design


def _new_rev(scene) -> None:
    """A random revision, not a counter: after an undo and a different edit a counter could repeat a cached one."""
    scene.skinsafe.design_rev = random.randrange(1, 2 ** 31)


def clear_text(scene) -> None:
    """Forget the stored design (its text and cache); the module objects stay."""
    text = bpy.data.texts.get(TEXT_NAME)
    if text is not None:
        bpy.data.texts.remove(text)
    _new_rev(scene)
    _designs.pop(scene.name, None)


def clear_design(scene) -> None:
    """Remove the design and every module object."""
    for o in [o for o in scene.objects if o.skinsafe_module.is_module]:
        bpy.data.objects.remove(o, do_unlink=True)
    clear_text(scene)


def new_module_object(scene, body_obj, module, placed, settings) -> bpy.types.Object:
    """A module object on its body object, its origin and axes at the placement's anchor frame."""
    obj = bpy.data.objects.new(module.name, bpy.data.meshes.new(module.name))
    body_obj.users_collection[0].objects.link(obj)
    obj.parent = body_obj
    obj.matrix_parent_inverse.identity()
    mm = obj.skinsafe_module
    mm.is_module, mm.module_id, mm.body, mm.owner = True, module.id, module.body, obj.session_uid
    for k in ("template", "method", "rows", "cols", "pitch", "taxel_diameter", "margin", "min_bend_radius", "max_strain",
              "outline", "mirrored"):
        setattr(mm.settings, k, getattr(settings, k))
    set_module_transform(obj, placed)
    return obj


def set_module_transform(obj, placed) -> None:
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = placed.origin_frame, placed.origin
    obj.matrix_basis = to_matrix(M)
    obj.skinsafe_module.placed_matrix = matrix_key(obj)
    module_mesh(obj, placed.positions, placed.frames, placed.module.taxel_diameter)


def module_mesh_key(obj) -> None:
    """Keep the key of the module mesh just made (a later edit of the data changes it)."""
    obj.skinsafe_module.mesh_key = b2c_mesh_key(obj.data)

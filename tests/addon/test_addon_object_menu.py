"""Every edit of Blender's Object menu and outliner that can change a module or a robot link keeps the skin
true (addon/integrity.py): a table of Blender's own operators, walked on one scene with modules on two links.
After each edit (then its undo, its redo, and its undo again, back to the scene for the next row): one module per
module object, taxel ids unique and stable (module id x 65,536 + index), every mesh's pads at its design taxels,
every pad on its link within 1 mm, every link at the robot's pose, and the modules the row does not edit unchanged
to 1e-6 m. Add an operator to OPS and it is tested. Headless Blender pushes an undo step only when asked
(`ed.undo_push`, what the window manager does after each operator)."""
import json
import tempfile
from pathlib import Path

import bpy
import mujoco
import numpy as np
import pytest

from skinsafe.addon import blender_to_core as b2c
from skinsafe.core.design.surface import cached_surfaces
from skinsafe.core.skin import taxel_map
from skinsafe.core.skin.ids import SHIFT

pytestmark = pytest.mark.xdist_group("object-menu")  # one worker walks the table on one scene, built once
E = 0.13585 - 0.1197  # UR5 forearm capsule axis height (body frame), radius 0.04
UP = 0.13585 + 0.06  # a point above the upper arm's axis
MODULES = {0: ("forearm_link", (-0.3, 0, E + 0.05)), 1: ("forearm_link", (-0.06, 0, E + 0.05)),
           2: ("upper_arm_link", (-0.2, 0, UP)), 3: ("upper_arm_link", (-0.34, 0, UP))}  # 3: a curve's outline
OUTLINE = [(-0.03, -0.02), (0.03, -0.02), (0.03, 0.0), (0.0, 0.025), (-0.03, 0.02)]


def _curve(name: str, points) -> bpy.types.Object:
    """A closed poly curve object in the scene."""
    cu = bpy.data.curves.new(name, "CURVE")
    sp = cu.splines.new("POLY")
    sp.points.add(len(points) - 1)
    for p, (x, y) in zip(sp.points, points):
        p.co = (x, y, 0.0, 1.0)
    sp.use_cyclic_u = True
    o = bpy.data.objects.new(name, cu)
    bpy.context.scene.collection.objects.link(o)
    return o


@pytest.fixture(scope="module")
def scene():
    bpy.ops.wm.read_homefile(use_empty=True)
    b2c.clear_caches()
    bpy.ops.skinsafe.import_robot(source="ur5")
    s = bpy.context.scene.skinsafe.new_module
    s.rows, s.cols, s.pitch, s.taxel_diameter, s.margin = 8, 8, 0.01, 0.006, 0.002
    for mid, (body, anchor) in MODULES.items():
        if mid == 3:
            s.template, s.outline = "curve", _curve("outline", OUTLINE)
        assert bpy.ops.skinsafe.place_module(body=body, anchor=anchor, direction=(-1, 0, 0), use_cursor=False) \
            == {"FINISHED"}
    s.template = "rect"
    bpy.ops.ed.undo_push(message="Place Module")
    LINK_MESHES.update({body: _mesh_sum(o) for body, o in b2c.body_objects(bpy.context.scene).items()})
    return bpy.context.scene


LINK_MESHES = {}  # body -> its mesh as imported from the robot description (`_mesh_sum`)


def _mesh_sum(o) -> np.ndarray:
    """A link object's mesh in a few numbers: its vertex count and 16 of its vertices spread over it (local)."""
    if o.type != "MESH":
        return np.zeros(1)
    v = o.data.vertices
    return np.r_[len(v), np.ravel([v[int(i)].co for i in np.linspace(0, len(v) - 1, min(len(v), 16))])]


def obj(name: str):
    return bpy.data.objects[name]


def module(mid: int):
    return next(o for o in b2c.module_objects(bpy.context.scene) if o.skinsafe_module.module_id == mid)


def select(*objs, mode="OBJECT"):
    for o in bpy.context.scene.objects:
        o.select_set(False)
    for o in objs:
        o.select_set(True)
    bpy.context.view_layer.objects.active = objs[0]


def state() -> dict:
    """module id -> (object name, taxel ids, world positions), after checking the objects against the design."""
    scene = bpy.context.scene
    bpy.context.view_layer.update()
    design = b2c.design_of(scene)
    objs = b2c.module_objects(scene)
    assert sorted(m.id for m in design.modules) == sorted(o.skinsafe_module.module_id for o in objs)  # one each
    t = design.taxels
    assert len(np.unique(t.ids)) == len(t.ids)
    robot = b2c.robot_for(scene)
    d = mujoco.MjData(robot.model)
    d.qpos[:] = b2c.pose(scene)
    mujoco.mj_kinematics(robot.model, d)
    bodies = b2c.body_objects(scene)
    for body, o in bodies.items():  # every link in the scene, at the pose, its mesh the robot description's
        assert o.name in scene.objects
        np.testing.assert_allclose(_mesh_sum(o), LINK_MESHES[body], rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(np.array(o.matrix_world)[:3, 3], d.xpos[robot.model.body(body).id], atol=1e-5)
    out = {}
    for o in objs:
        mid = o.skinsafe_module.module_id
        (m,) = [m for m in design.modules if m.id == mid]
        on = np.flatnonzero(t.module == mid)
        assert m.name == o.name and o.type == "MESH" and len(on) == len(o.data.polygons)
        assert len(on) == (m.rows * m.cols if m.template == "rect" else 21)  # the outline's 21 cells
        assert np.array_equal(t.ids[on], (mid << SHIFT) + np.arange(len(on)))
        surf = cached_surfaces(robot.model, [m.body])[m.body]
        assert surf.closest(t.positions[on])[3].max() < 1e-3  # pads on their link
        W = np.array(bodies[m.body].matrix_world)
        world = t.positions[on] @ W[:3, :3].T + W[:3, 3]
        assert o.parent is bodies[m.body]
        M = W @ np.array(o.matrix_parent_inverse) @ np.array(o.matrix_basis)  # matrix_world, also where not evaluated
        co = np.empty(len(o.data.vertices) * 3)
        o.data.vertices.foreach_get("co", co)
        np.testing.assert_allclose(co.reshape(-1, 6, 3).mean(axis=1) @ M[:3, :3].T + M[:3, 3], world, atol=2e-4)
        out[mid] = (o.name, t.ids[on].copy(), world)
    return out


def same(a: dict, b: dict, ids=None):
    assert set(ids if ids is not None else a) <= set(b)
    for mid in ids if ids is not None else a:
        assert a[mid][0] == b[mid][0] and np.array_equal(a[mid][1], b[mid][1])
        np.testing.assert_allclose(a[mid][2], b[mid][2], atol=1e-6)


def _apply(**kw):
    select(module(0))
    return bpy.ops.object.transform_apply(**kw)


def _join():
    select(module(1), module(0))
    return bpy.ops.object.join()


def _separate():
    select(module(0))
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.mesh.select_all(action="SELECT")
    r = bpy.ops.mesh.separate(type="LOOSE")
    bpy.ops.object.mode_set(mode="OBJECT")
    return r


def _parent_to(link: str, keep: bool):
    select(module(0), obj(link))
    bpy.context.view_layer.objects.active = obj(link)
    return bpy.ops.object.parent_set(type="OBJECT", keep_transform=keep)


def _on_link(name: str, op, **kw):
    select(obj(name))
    return op(**kw)


def _modifier_applied():
    select(module(0))
    bpy.ops.object.modifier_add(type="SUBSURF")
    return bpy.ops.object.modifier_apply(modifier=module(0).modifiers[0].name)


def _dup_in_place_then_delete_original(linked=False):
    select(module(1))
    bpy.ops.object.duplicate(linked=linked)  # Shift+D (Alt+D: linked), cancelled where it stands
    bpy.context.view_layer.update()
    select(module(1))
    return bpy.ops.object.delete()


def _exported(after):
    """File > Export's taxel map holds the scene's pads, each where its object shows it."""
    with tempfile.TemporaryDirectory() as tmp:
        path = f"{tmp}/skin.json"
        assert bpy.ops.skinsafe.export_taxel_map(filepath=path) == {"FINISHED"}
        d = taxel_map.load(path)
    bodies = b2c.body_objects(bpy.context.scene)
    assert d.n_taxels == sum(len(o.data.polygons) for o in b2c.module_objects(bpy.context.scene))
    for mid, (_, ids, world) in after.items():
        on = d.taxels.module == mid
        W = np.array(bodies[d.body_of(int(np.argmax(on)))].matrix_world)
        assert np.array_equal(d.taxels.ids[on], ids)
        np.testing.assert_allclose(d.taxels.positions[on] @ W[:3, :3].T + W[:3, 3], world, atol=1e-6)


def _ids_retired(before, after):
    """The module deleted (the newest: its id is the one a counter would give again) leaves for good, kept in the
    taxel map's retired ids: the next module placed takes a new id, never its."""
    assert sorted(after) == [0, 1, 2]
    assert bpy.ops.skinsafe.place_module(body="upper_arm_link", anchor=MODULES[3][1], direction=(-1, 0, 0),
                                         use_cursor=False) == {"FINISHED"}
    assert sorted(state()) == [0, 1, 2, 4]
    assert json.loads(bpy.data.texts[b2c.TEXT_NAME].as_string())["retired_modules"] == [3]


def _dup_entered(before, after):
    """The copy left in place enters the design once its original is deleted: the export holds the scene's pads."""
    (new,) = set(after) - set(before)
    assert sorted(after) == [0, 2, 3, new] and new == 4
    np.testing.assert_allclose(after[new][2], before[1][2], atol=1e-6)  # the copy, where the original was
    _exported(after)


def _elbow_moves(before):
    """The elbow turns: every module's pads stay on their link (`state`), then it turns back."""
    joint = bpy.context.scene.skinsafe.joints["elbow_joint"]
    joint.value += 0.3
    moved = state()
    joint.value -= 0.3
    same(before, state())
    return moved


def _put_back(before, after):
    """Parented to a link it does not lie on: put back on its own, and said; it stays there when the elbow turns."""
    same(before, after)
    assert "put back on 'forearm_link'" in bpy.context.scene.skinsafe.message
    assert b2c.body_objects(bpy.context.scene)["forearm_link"] is module(0).parent
    _elbow_moves(after)


def _move_joint_then(before, after):
    same(before, after)
    assert not b2c.stray_bodies(bpy.context.scene)  # the robot's own link, not a copy
    _elbow_moves(after)  # the link moved into a collection still poses


def _link_put_back(before, after):
    """A robot link deleted is put back, and Check's export (the design) is the scene's."""
    same(before, after)
    assert "cannot be deleted" in bpy.context.scene.skinsafe.message
    _exported(after)


def _then_moved(mid: int, taxels: int):
    """After the edit, the next 2 cm move of module `mid` along its link moves its pads 2 cm (within 1 mm) and keeps
    its `taxels`; the move is undone again (one undo step of its own)."""
    def check(before, after):
        same(before, after)
        o = module(mid)
        W = np.array(o.parent.matrix_world)
        select(o)
        assert bpy.ops.transform.translate(value=tuple(W[:3, 0] * 0.02)) == {"FINISHED"}
        bpy.ops.ed.undo_push(message="Move")
        moved = state()
        same(before, moved, ids=[m for m in before if m != mid])
        assert len(moved[mid][1]) == taxels
        np.testing.assert_allclose(moved[mid][2], before[mid][2] + W[:3, 0] * 0.02, atol=1e-3)
        assert bpy.ops.ed.undo() == {"FINISHED"}
        same(after, state())
    return check


def _snap_to_cursor():
    """Shift+S Selection to Cursor: the cursor on the forearm's top between modules 0 and 1."""
    W = np.array(obj("forearm_link").matrix_world)
    bpy.context.scene.cursor.location = W[:3, :3] @ (-0.18, 0, E + 0.04) + W[:3, 3]
    module(0).matrix_world.translation = bpy.context.scene.cursor.location  # what the operator sets
    return {"FINISHED"}


def _snapped(before, after):
    same(before, after, ids=[1, 2])
    W = np.array(obj("forearm_link").matrix_world)
    np.testing.assert_allclose(after[0][2], before[0][2] + W[:3, 0] * 0.12, atol=1e-3)  # 12 cm along, re-placed


def _joined(before, after):
    same(before, after)
    assert "split back" in bpy.context.scene.skinsafe.message


def _curve_module_joined(before, after):
    """A curve module split back takes its outline curve again (the one it had, still in the scene)."""
    _joined(before, after)
    assert module(3).skinsafe_module.settings.outline is bpy.data.objects["outline"]


def _join_into(active):
    """Ctrl+J with a module selected and `active` (a robot link, any mesh) the active object."""
    def edit():
        target = active()
        select(target, module(0))
        return bpy.ops.object.join()
    return edit


def _plane():
    bpy.ops.mesh.primitive_plane_add(size=0.1, location=(1, 1, 0))
    return bpy.context.active_object


def _joined_into_plane(before, after):
    _joined(before, after)
    assert len(bpy.data.objects["Plane"].data.polygons) == 1  # the module's pads cut out of it


def _outline_join(outline_active: bool):
    """Ctrl+J of the curve module's outline with another curve (the outline joined away, or another curve into it)."""
    def edit():
        other = _curve("other curve", [(0, 0), (0.1, 0), (0.1, 0.1)])
        outline = module(3).skinsafe_module.settings.outline
        select(*((outline, other) if outline_active else (other, outline)))
        return bpy.ops.object.join()
    return edit


def _outline_kept(before, after):
    """The module's outline is made again from the design, said; its next move keeps its cells."""
    assert "outline curve was joined, converted or deleted" in bpy.context.scene.skinsafe.message
    cu = module(3).skinsafe_module.settings.outline
    assert cu.type == "CURVE" and len(cu.data.splines) == 1
    np.testing.assert_allclose([tuple(p.co[:2]) for p in cu.data.splines[0].points], OUTLINE, atol=1e-6)
    _then_moved(3, len(before[3][1]))(before, after)


def _link_copy_named(before, after):
    """Shift+D on a robot link: the copy is named for deletion (it is not the robot's), the design unchanged."""
    same(before, after)
    scene = bpy.context.scene
    (copy,) = b2c.stray_bodies(scene)
    assert copy.startswith("forearm_link.") and copy in scene.skinsafe.error and "delete them" in scene.skinsafe.error


# (the edit, what it does; check(before, after), None: every module as before)
def _on_module(mid: int, op, **kw):
    select(module(mid))
    return op(**kw)


OPS = [
    ("Apply > All Transforms on a module", lambda: _apply(location=True, rotation=True, scale=True), _then_moved(0, 64)),
    ("Apply > Location on a module", lambda: _apply(location=True, rotation=False, scale=False), _then_moved(0, 64)),
    ("Apply > Rotation on a module", lambda: _apply(location=False, rotation=True, scale=False), _then_moved(0, 64)),
    ("Apply > Scale on a module", lambda: _apply(location=False, rotation=False, scale=True), None),
    ("Set Origin to Geometry on a module", lambda: _on_module(0, bpy.ops.object.origin_set, type="ORIGIN_GEOMETRY"),
     None),
    ("Set Origin to 3D Cursor on a module", lambda: _on_module(0, bpy.ops.object.origin_set, type="ORIGIN_CURSOR"),
     _then_moved(0, 64)),
    ("Apply a modifier on a module", _modifier_applied, None),
    ("Snap a module to the cursor", _snap_to_cursor, _snapped),
    ("Shade Smooth on a module", lambda: _on_module(0, bpy.ops.object.shade_smooth), None),
    ("Shade Flat on a module", lambda: _on_module(0, bpy.ops.object.shade_flat), None),
    ("Convert to Curve a module", lambda: _on_module(0, bpy.ops.object.convert, target="CURVE"), None),
    ("Convert to Mesh a module", lambda: _on_module(0, bpy.ops.object.convert, target="MESH"), None),
    ("Ctrl+P to another link", lambda: _parent_to("upper_arm_link", False), _put_back),
    ("Ctrl+P to another link, Keep Transform", lambda: _parent_to("upper_arm_link", True), _put_back),
    ("Alt+P Clear Parent on a module", lambda: _on_module(0, bpy.ops.object.parent_clear, type="CLEAR"), None),
    ("Alt+P Clear and Keep Transformation on a module",
     lambda: _on_module(0, bpy.ops.object.parent_clear, type="CLEAR_KEEP_TRANSFORM"), None),
    ("Ctrl+J two modules", _join, _joined),
    ("Ctrl+J a module into a robot link", _join_into(lambda: obj("forearm_link")), _joined),
    ("Ctrl+J a curve module into another module", lambda: (select(module(2), module(3)), bpy.ops.object.join())[1],
     _curve_module_joined),
    ("Ctrl+J a module into another mesh", _join_into(_plane), _joined_into_plane),
    ("Ctrl+J a curve module's outline into another curve", _outline_join(False), _outline_kept),
    ("Ctrl+J another curve into a curve module's outline", _outline_join(True), _outline_kept),
    ("Convert a curve module's outline to a mesh",
     lambda: (select(module(3).skinsafe_module.settings.outline), bpy.ops.object.convert(target="MESH"))[1],
     _outline_kept),
    ("P Separate a module by loose parts", _separate, None),
    ("Shift+D in place, then the original deleted", _dup_in_place_then_delete_original, _dup_entered),
    ("Alt+D in place, then the original deleted", lambda: _dup_in_place_then_delete_original(linked=True),
     _dup_entered),
    ("X on a module; the next module placed", lambda: _on_module(3, bpy.ops.object.delete), _ids_retired),
    # H and the outliner's eye and screen: what object.hide_view_set does (its poll needs a viewport)
    ("Hide a module", lambda: module(0).hide_set(True) or {"FINISHED"}, None),
    ("Disable a module in viewports", lambda: setattr(module(0), "hide_viewport", True) or {"FINISHED"}, None),
    ("Disable a module in renders", lambda: setattr(module(0), "hide_render", True) or {"FINISHED"}, None),
    ("Add a Collection Instance of the robot",
     lambda: bpy.ops.object.collection_instance_add(collection=b2c.COLLECTION), None),
    ("Move a module to a new collection",
     lambda: (select(module(0)), bpy.ops.object.move_to_collection(collection_uid=bpy.context.scene.collection.session_uid, is_new=True,
                                                                 new_collection_name="pads"))[1], None),
    ("Link a module to a new collection",
     lambda: (select(module(0)), bpy.ops.object.link_to_collection(collection_uid=bpy.context.scene.collection.session_uid, is_new=True,
                                                                 new_collection_name="pads"))[1], None),
    ("X on a robot link", lambda: _on_link("forearm_link", bpy.ops.object.delete), _link_put_back),
    ("Shift+D on a robot link", lambda: _on_link("forearm_link", bpy.ops.object.duplicate), _link_copy_named),
    ("Apply > All Transforms on a robot link",
     lambda: _on_link("forearm_link", bpy.ops.object.transform_apply, location=True, rotation=True, scale=True), None),
    ("Set Origin on a robot link", lambda: _on_link("forearm_link", bpy.ops.object.origin_set, type="ORIGIN_GEOMETRY"),
     None),
    ("Apply a modifier on a robot link", lambda: (_on_link("forearm_link", bpy.ops.object.modifier_add, type="DISPLACE"),
                                                  bpy.ops.object.modifier_apply(modifier="Displace"))[1], None),
    ("Ctrl+P a robot link to a module", lambda: (select(module(2), obj("forearm_link")),
                                                 bpy.ops.object.parent_set(type="OBJECT"))[1], None),
    ("G on a robot link", lambda: _on_link("forearm_link", bpy.ops.transform.translate, value=(0.05, 0, 0)), None),
    ("Alt+P Clear Parent on a robot link", lambda: _on_link("forearm_link", bpy.ops.object.parent_clear,
                                                            type="CLEAR"), None),
    ("Convert a robot link to a curve", lambda: _on_link("forearm_link", bpy.ops.object.convert, target="CURVE"), None),
    ("Move a robot link to a new collection",
     lambda: _on_link("forearm_link", bpy.ops.object.move_to_collection, collection_uid=bpy.context.scene.collection.session_uid, is_new=True,
                      new_collection_name="links"), _move_joint_then),
]


@pytest.mark.parametrize("name,edit,check", OPS, ids=[o[0] for o in OPS])
def test_an_object_menu_edit_keeps_the_skin_true_through_undo_and_redo(scene, name, edit, check):
    before = state()
    assert edit() in ({"FINISHED"}, {"CANCELLED"})
    bpy.context.view_layer.update()
    bpy.ops.ed.undo_push(message=name)
    after = state()
    (check or same)(before, after)
    assert bpy.ops.ed.undo() == {"FINISHED"}
    same(before, state())
    assert bpy.ops.ed.redo() == {"FINISHED"}
    same(after, state(), ids=[m for m in after if m in state()])
    assert bpy.ops.ed.undo() == {"FINISHED"}
    same(before, state())


def test_a_copy_left_on_its_original_is_named_on_the_object_and_in_check(scene):
    scene = bpy.context.scene  # the fixture's struct is gone after the undo steps above
    select(module(1))
    bpy.ops.object.duplicate()  # Shift+D, cancelled where it stands: on top of module 1
    bpy.context.view_layer.update()
    bpy.ops.ed.undo_push(message="Duplicate")
    scene = bpy.context.scene
    (copy,) = [o for o in b2c.module_objects(scene) if o.skinsafe_module.module_id not in MODULES]
    assert "overlaps module 1" in copy.skinsafe_module.error
    with pytest.raises(RuntimeError, match="problems, listed in Skin > Check"):
        bpy.ops.skinsafe.check(poses=1)
    first = scene.skinsafe_findings[0]
    assert f"'{copy.name}' is not where the design has it" in first.text and first.module_id == 4
    assert bpy.ops.ed.undo() == {"FINISHED"}
    assert sorted(state()) == [0, 1, 2, 3]


def test_the_docs_list_every_edit_of_the_table():
    """docs/design/blender.md's table of edits holds exactly the rows of OPS, each with what it does to a skin."""
    text = (Path(__file__).parents[2] / "docs/design/blender.md").read_text()
    table = text.split("| edit (a row of the test's table) | what it does to the skin |\n| --- | --- |\n")[1]
    rows = [line.split(" | ") for line in table.split("\n\n")[0].splitlines()]
    assert [r[0].removeprefix("| ") for r in rows] == [o[0] for o in OPS]
    assert all(len(r) == 2 and len(r[1]) > 10 for r in rows)

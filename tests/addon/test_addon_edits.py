"""The design follows the module objects through every ordinary edit, headless, with Blender's own
operators (object.duplicate_move, object.delete, transform.resize / mirror, view3d.copybuffer /
pastebuffer, wm.append, ed.undo / ed.redo, wm.open_mainfile): after each edit the module count, the
module ids, each module's taxel count, ids and positions agree with the objects (the taxel centres of
each module's mesh are its design taxels), and taxels of the modules not edited keep their ids and
places. Undo needs `ed.undo_push`: Blender pushes a step after each operator only with a window, so
each edit here is followed by the push the window manager would do."""
import json
from pathlib import Path

import bpy
import numpy as np
import pytest
from mathutils import Matrix, Vector

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import core_to_blender as c2b
from skinsafe.addon import edits
from skinsafe.core.skin.ids import SHIFT
from skinsafe.hardware.board_config import board_configs

E = 0.13585 - 0.1197  # UR5 forearm capsule axis height (body frame), radius 0.04
UP = 0.13585 + 0.06  # a point above the upper arm's axis


def _place(body, anchor, direction=(-1, 0, 0), **settings):
    s = bpy.context.scene.skinsafe.new_module
    for k, v in {"template": "rect", "rows": 8, "cols": 8, "pitch": 0.01, "taxel_diameter": 0.006, "margin": 0.002,
                 "min_bend_radius": 0.01, "method": "geodesic", "mirrored": False, **settings}.items():
        setattr(s, k, v)
    assert bpy.ops.skinsafe.place_module(body=body, anchor=anchor, direction=direction, use_cursor=False) == {"FINISHED"}
    bpy.ops.ed.undo_push(message="Place Module")


@pytest.fixture
def scene():
    """UR5 with three 8x8 modules: A, B on the forearm (12 cm free between them), C on the upper arm (ids 0, 1, 2)."""
    bpy.ops.wm.read_homefile(use_empty=True)
    b2c.clear_caches()
    bpy.ops.ed.undo_push(message="start")
    bpy.ops.skinsafe.import_robot(source="ur5")
    bpy.ops.ed.undo_push(message="Import Robot")
    _place("forearm_link", (-0.3, 0, E + 0.05))
    _place("forearm_link", (-0.06, 0, E + 0.05))
    _place("upper_arm_link", (-0.2, 0, UP))
    return bpy.context.scene


def _objects(scene=None):
    return {o.name: o for o in b2c.module_objects(scene or bpy.context.scene)}


def _select(*objs):
    for o in bpy.context.scene.objects:
        o.select_set(False)
    for o in objs:
        o.select_set(True)
    bpy.context.view_layer.objects.active = objs[0]


def _axis(body: str) -> np.ndarray:
    """The body's x axis in the world (the forearm's and upper arm's length)."""
    return np.array(b2c.body_objects(bpy.context.scene)[body].matrix_world)[:3, 0]


def _state(scene=None) -> dict:
    """module id -> (object name, taxel ids, world positions) of the design, after checking it against the
    objects: one module per module object, ids unique, each mesh's taxel centres = its design taxels."""
    scene = scene or bpy.context.scene
    bpy.context.view_layer.update()
    design = b2c.design_of(scene)
    objs = b2c.module_objects(scene)
    assert sorted(m.id for m in design.modules) == sorted(o.skinsafe_module.module_id for o in objs)
    t = design.taxels
    assert len(np.unique(t.ids)) == len(t.ids)
    out = {}
    for o in objs:
        mid = o.skinsafe_module.module_id
        (m,) = [m for m in design.modules if m.id == mid]
        on = np.flatnonzero(t.module == mid)
        assert m.name == o.name and len(on) == len(o.data.polygons)
        assert m.template != "rect" or len(on) == m.rows * m.cols
        assert np.array_equal(t.ids[on], (mid << SHIFT) + np.arange(len(on)))  # module uid + index
        W = np.array(b2c.body_objects(scene)[m.body].matrix_world)
        world = t.positions[on] @ W[:3, :3].T + W[:3, 3]
        np.testing.assert_allclose(c2b.module_taxel_centres(o), world, atol=2e-4)
        out[mid] = (o.name, t.ids[on].copy(), world)
    return out


def _same(a: dict, b: dict, ids=None):
    for mid in ids if ids is not None else a:
        assert a[mid][0] == b[mid][0] and np.array_equal(a[mid][1], b[mid][1])
        np.testing.assert_allclose(a[mid][2], b[mid][2], atol=1e-9)


def test_duplicate_gets_its_own_id_and_taxels_delete_removes_it_undo_redo_restore(scene):
    before = _state()
    assert sorted(before) == [0, 1, 2]
    a = _objects()["forearm_link_module0"]
    _select(a)
    assert bpy.ops.object.duplicate_move(TRANSFORM_OT_translate={"value": tuple(_axis("forearm_link") * 0.12)}) \
        == {"FINISHED"}
    bpy.ops.ed.undo_push(message="Duplicate Objects")
    dup = _state()
    assert sorted(dup) == [0, 1, 2, 3]  # the copy is module 3, with 64 taxels of its own
    _same(before, dup)  # the original and the others untouched
    name, ids, world = dup[3]
    assert name == "forearm_link_module0.001" and len(ids) == 64
    np.testing.assert_allclose(world, before[0][2] + _axis("forearm_link") * 0.12, atol=1e-6)

    _select(_objects()[name])
    assert bpy.ops.object.delete() == {"FINISHED"}
    bpy.ops.ed.undo_push(message="Delete")
    gone = _state()
    assert sorted(gone) == [0, 1, 2] and b2c.design_of(bpy.context.scene).n_taxels == 192
    _same(before, gone)

    assert bpy.ops.ed.undo() == {"FINISHED"}  # the copy and its taxels are back
    _same(dup, _state())
    assert bpy.ops.ed.undo() == {"FINISHED"}  # before the duplicate
    _same(before, _state())
    assert sorted(_state()) == [0, 1, 2]
    assert bpy.ops.ed.redo() == {"FINISHED"}
    _same(dup, _state())
    assert bpy.ops.ed.redo() == {"FINISHED"}
    _same(gone, _state())


def test_copy_paste_in_place_is_named_then_placed_where_moved(scene):
    before = _state()
    _select(_objects()["forearm_link_module1"])
    assert bpy.ops.view3d.copybuffer() == {"FINISHED"}
    assert bpy.ops.view3d.pastebuffer() == {"FINISHED"}  # on top of the original
    bpy.context.view_layer.update()
    (pasted,) = [o for o in b2c.module_objects(bpy.context.scene) if o.name.startswith("forearm_link_module1.")]
    assert pasted.skinsafe_module.module_id == 3 and "overlaps module 1" in pasted.skinsafe_module.error
    assert sorted(m.id for m in b2c.design_of(bpy.context.scene).modules) == [0, 1, 2]  # named, not in the design
    pasted.matrix_world = Matrix.Translation(Vector(_axis("forearm_link") * -0.12)) @ pasted.matrix_world
    after = _state()  # moved clear: it enters the design
    assert sorted(after) == [0, 1, 2, 3] and pasted.skinsafe_module.error == ""
    _same(before, after)
    np.testing.assert_allclose(after[3][2], before[1][2] - _axis("forearm_link") * 0.12, atol=1e-6)


def test_append_from_another_file_takes_the_robots_link_and_a_fresh_id(scene, tmp_path):
    other = tmp_path / "other.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(other), copy=True)
    before = _state()
    lib = f"{other}/Object/"
    assert bpy.ops.wm.append(filepath=lib + "forearm_link_module0", directory=lib,
                             filename="forearm_link_module0") == {"FINISHED"}
    bpy.context.view_layer.update()
    (new,) = [o for o in b2c.module_objects(bpy.context.scene) if o.name == "forearm_link_module0.001"]
    assert new.skinsafe_module.module_id == 3
    assert new.parent is b2c.body_objects(bpy.context.scene)["forearm_link"]  # not the appended link copy
    assert "overlaps module 0" in new.skinsafe_module.error  # it came to module 0's place: named
    assert any("copies of robot links" in e for e in edits.step(bpy.context.scene))
    new.matrix_world = Matrix.Translation(Vector(_axis("forearm_link") * 0.12)) @ new.matrix_world
    after = _state()
    _same(before, after)
    np.testing.assert_allclose(after[3][2], before[0][2] + _axis("forearm_link") * 0.12, atol=1e-6)


def test_rename_follows_and_other_modules_keep_ids_through_resize_and_delete(scene):
    before = _state()
    b = _objects()["forearm_link_module1"]
    b.name = "elbow pad"
    renamed = _state()
    assert renamed[1][0] == "elbow pad" and b2c.design_of(bpy.context.scene).modules[1].name == "elbow pad"
    _same(before, renamed, ids=[0, 2])
    _select(_objects()["forearm_link_module0"])
    bpy.ops.transform.resize(value=(0.5, 1.0, 1.0), orient_type="LOCAL")
    resized = _state()
    assert len(resized[0][1]) == 32 and _objects()["forearm_link_module0"].skinsafe_module.settings.cols == 4
    _same(renamed, resized, ids=[1, 2])  # stable ids: the others keep theirs
    _select(_objects()["elbow pad"])
    bpy.ops.object.delete()
    left = _state()
    assert sorted(left) == [0, 2]
    _same(resized, left, ids=[0, 2])
    ids = {int(e["taxel_id"]) for cfg in board_configs(b2c.design_of(bpy.context.scene)) for e in cfg.entries}
    assert ids == set(np.concatenate([left[0][1], left[2][1]]).tolist())  # the boards carry the same ids


def test_scale_applies_once_at_the_end_of_the_drag_and_a_misfit_is_refused(scene):
    a = _objects()["forearm_link_module0"]
    before = _state()
    # a drag: every update sees the transform running (Window.modal_operators holds TRANSFORM_OT_resize),
    # which headless has no window for: the handler's step for it is run by hand
    for s in (1.2, 1.25, 1.3, 1.25):
        a.scale = (s, 1.0, 1.0)
        edits.step(bpy.context.scene, apply_scale=False)
        assert a.skinsafe_module.settings.cols == 8 and tuple(a.scale)[0] == pytest.approx(s)
    _same(before, {k: v for k, v in _state_no_update().items()})
    edits.step(bpy.context.scene)  # the drag ended
    assert a.skinsafe_module.settings.cols == 10 and tuple(a.scale) == (1.0, 1.0, 1.0)
    assert len(_state()[0][1]) == 80
    a.scale = (1.3, 1.0, 1.0)  # a cancelled drag: back at 1 when it ends, nothing applied
    edits.step(bpy.context.scene, apply_scale=False)
    a.scale = (1.0, 1.0, 1.0)
    assert len(_state()[0][1]) == 80
    c = _objects()["upper_arm_link_module2"]
    _select(c)
    bpy.ops.transform.resize(value=(10.0, 1.0, 1.0), orient_type="LOCAL")  # 80 columns: off the link
    bpy.context.view_layer.update()
    assert "falls off the surface" in c.skinsafe_module.error and c.skinsafe_module.settings.cols == 8
    assert tuple(c.scale) == (1.0, 1.0, 1.0)
    _same(before, _state(), ids=[1, 2])


def _state_no_update():
    """module id -> (name, ids, world positions) straight from the design (no depsgraph update)."""
    scene = bpy.context.scene
    design = b2c.design_of(scene)
    t = design.taxels
    out = {}
    for m in design.modules:
        on = t.module == m.id
        W = np.array(b2c.body_objects(scene)[m.body].matrix_world)
        out[m.id] = (m.name, t.ids[on].copy(), t.positions[on] @ W[:3, :3].T + W[:3, 3])
    return out


def test_mirror_makes_the_mirrored_module_and_undo_restores(scene):
    a = _objects()["forearm_link_module0"]
    before = _state()
    _select(a)
    assert bpy.ops.transform.mirror(constraint_axis=(True, False, False), orient_type="LOCAL") == {"FINISHED"}
    bpy.ops.ed.undo_push(message="Mirror")
    mirrored = _state()
    st = a.skinsafe_module.settings
    assert (st.rows, st.cols, st.mirrored) == (8, 8, True) and np.linalg.det(np.array(a.matrix_basis)) > 0
    # taxel k (row r, col c) sits where the template's mirror image puts it: the original's (r, 7 - c)
    k = np.arange(64)
    mirror_of = (k // 8) * 8 + 7 - k % 8
    np.testing.assert_allclose(mirrored[0][2], before[0][2][mirror_of], atol=1e-6)  # anchor read back in float32
    assert np.array_equal(mirrored[0][1], before[0][1])  # the same module: the same ids
    _same(before, mirrored, ids=[1, 2])
    F = b2c.design_of(bpy.context.scene).taxels.frames
    assert np.allclose(np.linalg.det(F), 1.0)  # right-handed frames
    bpy.ops.transform.mirror(constraint_axis=(False, True, False), orient_type="LOCAL")  # y: mirrored back, turned
    bpy.ops.ed.undo_push(message="Mirror")
    turned = _state()
    assert not st.mirrored and len(turned[0][1]) == 64
    np.testing.assert_allclose(turned[0][2][::-1], before[0][2], atol=5e-4)  # a half turn: taxel k at 63 - k
    assert bpy.ops.ed.undo() == {"FINISHED"}
    _same(mirrored, _state())
    assert _objects()["forearm_link_module0"].skinsafe_module.settings.mirrored
    assert bpy.ops.ed.undo() == {"FINISHED"}
    _same(before, _state())
    assert not _objects()["forearm_link_module0"].skinsafe_module.settings.mirrored


def test_file_reload_keeps_the_design_and_repairs_a_file_saved_out_of_step(scene, tmp_path):
    before = _state()
    path = tmp_path / "skin.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.open_mainfile(filepath=str(path))
    _same(before, _state())
    # a file edited without the add-on: a module deleted, another duplicated (same id), then saved
    edits.unregister()
    try:
        objs = _objects()
        bpy.data.objects.remove(objs["forearm_link_module1"])
        copy = objs["upper_arm_link_module2"].copy()
        copy.data = copy.data.copy()
        objs["upper_arm_link_module2"].users_collection[0].objects.link(copy)
        copy.location.x -= 0.1
        text = bpy.data.texts[b2c.TEXT_NAME]  # and its design's taxel ids under the old rule (0..N-1)
        raw = json.loads(text.as_string())
        raw["taxels"]["ids"] = list(range(len(raw["taxels"]["ids"])))
        text.from_string(json.dumps(raw))
        bpy.ops.wm.save_as_mainfile(filepath=str(path))
    finally:
        edits.register()
    bpy.ops.wm.open_mainfile(filepath=str(path))  # load_post converts and repairs it
    message = bpy.context.scene.skinsafe.message
    assert "older taxel-id rule" in message and "need a new `skinsafe deploy`" in message
    after = _state()  # the stable ids
    assert sorted(after) == [0, 2, 3]
    _same(before, after, ids=[0, 2])
    assert json.loads(bpy.data.texts[b2c.TEXT_NAME].as_string())["taxels"]["ids"][64] == 2 << SHIFT  # stored so
    assert Path(path).exists()


def test_a_modules_settings_edit_regenerates_it_and_a_misfit_is_named(scene):
    before = _state()
    st = _objects()["forearm_link_module0"].skinsafe_module.settings
    st.rows = 4
    after = _state()
    assert len(after[0][1]) == 32
    _same(before, after, ids=[1, 2])
    c = _objects()["upper_arm_link_module2"]
    c.skinsafe_module.settings.cols = 80  # 80 cm of FPC on the upper arm: refused, the last taxels kept
    bpy.context.view_layer.update()
    assert "falls off the surface" in c.skinsafe_module.error
    _same(after, _state_no_update(), ids=[0, 1, 2])


def test_deleting_every_module_empties_the_design_and_undo_brings_it_back(scene):
    before = _state()
    _select(*b2c.module_objects(bpy.context.scene))
    assert bpy.ops.object.delete() == {"FINISHED"}
    bpy.ops.ed.undo_push(message="Delete")
    bpy.context.view_layer.update()
    assert b2c.design_of(bpy.context.scene) is None and b2c.TEXT_NAME not in bpy.data.texts
    assert bpy.ops.ed.undo() == {"FINISHED"}
    _same(before, _state())


def test_mirroring_a_curve_module_mirrors_its_outline(scene):
    cu = bpy.data.curves.new("outline", "CURVE")
    sp = cu.splines.new("POLY")
    corners = [(-0.04, -0.03), (0.04, -0.03), (0.04, -0.01), (-0.01, 0.03), (-0.04, 0.03)]  # no mirror symmetry
    sp.points.add(len(corners) - 1)
    for p, (x, y) in zip(sp.points, corners):
        p.co = (x, y, 0.0, 1.0)
    sp.use_cyclic_u = True
    outline = bpy.data.objects.new("outline", cu)
    bpy.context.scene.collection.objects.link(outline)
    c = _objects()["upper_arm_link_module2"]
    st = c.skinsafe_module.settings
    st.template, st.outline = "curve", outline
    before = _state()
    n = len(before[2][1])
    assert 0 < n < 64
    _select(c)
    bpy.ops.transform.mirror(constraint_axis=(True, False, False), orient_type="LOCAL")
    after = _state()
    assert st.mirrored and len(after[2][1]) == n
    # taxel k sits at the mirror image of the original taxel k: the same row, the mirrored column
    M = np.array(c.matrix_world)  # the module frame: x along the rows, anchor at its origin
    local = lambda w: (w - M[:3, 3]) @ M[:3, :3]  # noqa: E731
    a, b = local(before[2][2]), local(after[2][2])
    np.testing.assert_allclose(b[:, 1], a[:, 1], atol=2e-3)  # rows stay (up to the arm's curvature)
    np.testing.assert_allclose(b[:, 0], -a[:, 0], atol=2e-3)  # columns mirrored


def test_a_uniform_resize_scales_rows_and_columns_once(scene):
    before = _state()
    a = _objects()["forearm_link_module0"]
    _select(a)
    bpy.ops.transform.resize(value=(0.5, 0.5, 0.5), orient_type="LOCAL")  # S 0.5: half the rows and columns
    after = _state()
    st = a.skinsafe_module.settings
    assert (st.rows, st.cols, len(after[0][1])) == (4, 4, 16) and tuple(a.scale) == (1.0, 1.0, 1.0)
    _same(before, after, ids=[1, 2])
    bpy.context.view_layer.update()  # further updates apply nothing again
    assert (st.rows, st.cols) == (4, 4)

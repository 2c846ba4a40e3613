"""The add-on's Cover Link operator through bpy.ops, headless: a link filled around a module
placed by hand, one module object per new module, no overlaps, and a clear refusal when full."""
import bpy
import numpy as np
import pytest

from skinsafe.addon import blender_to_core as b2c
from skinsafe.core.design.cover import cover_report

E = 0.13585 - 0.1197  # UR5 forearm capsule axis height (body frame), radius 0.04


@pytest.fixture
def scene():
    bpy.ops.wm.read_homefile(use_empty=True)
    b2c.clear_caches()
    return bpy.context.scene


def _settings(**kw):
    s = bpy.context.scene.skinsafe.new_module
    for k, v in {"template": "rect", "rows": 3, "cols": 3, "pitch": 0.01, "taxel_diameter": 0.006, "margin": 0.001,
                 "min_bend_radius": 0.01, "method": "geodesic", **kw}.items():
        setattr(s, k, v)


def test_cover_link_fills_around_a_placed_module(scene):
    assert bpy.ops.skinsafe.import_robot(source="ur5") == {"FINISHED"}
    _settings(rows=4, cols=4)
    assert bpy.ops.skinsafe.place_module(body="forearm_link", anchor=(-0.2, 0.0, E + 0.04), direction=(-1, 0, 0),
                                         use_cursor=False) == {"FINISHED"}
    first = b2c.design_of(scene)
    assert bpy.ops.skinsafe.place_module(body="upper_arm_link", anchor=(-0.2, 0.0, 0.19585), direction=(-1, 0, 0),
                                         use_cursor=False) == {"FINISHED"}
    for o in scene.objects:
        o.select_set(o.skinsafe_module.module_id == 1)
    assert bpy.ops.object.delete() == {"FINISHED"}  # module 1 placed and deleted: its id is retired
    bpy.context.view_layer.update()
    _settings()
    assert bpy.ops.skinsafe.cover_link(body="forearm_link") == {"FINISHED"}
    design = b2c.design_of(scene)
    # the hand-placed module is kept as it was, numbered first; every new module has its object and a new id
    np.testing.assert_array_equal(design.taxels.positions[design.taxels.module == 0], first.taxels.positions)
    assert sorted(m.id for m in design.modules)[:2] == [0, 2] and design.retired_modules == (1,)
    objects = b2c.module_objects(scene)
    assert sorted(o.skinsafe_module.module_id for o in objects) == sorted(m.id for m in design.modules)
    assert {o.name for o in objects} == {m.name for m in design.modules}
    assert all(o.parent.name == b2c.body_objects(scene)["forearm_link"].name for o in objects)
    assert {(m.rows, m.cols) for m in design.modules[1:]} <= {(3, 3), (2, 3), (2, 2), (1, 3), (1, 2)}
    assert len(design.modules) > 40
    # no two modules' taxels closer than 3/4 pitch (their cells would overlap): checked here directly
    t = design.taxels
    d = np.linalg.norm(t.positions[:, None] - t.positions[None], axis=2)
    other = t.module[:, None] != t.module[None]
    assert d[other].min() >= 0.75 * 0.01 - 1e-9
    row = cover_report(design, b2c.robot_for(scene).model, b2c.robot_for(scene).home)["forearm_link"]
    assert row["covered"] > 0.8 and row["overlaps"] == 0 and row["buried"] == 0
    assert f"{row['taxels']} taxels" in scene.skinsafe.message
    # covering it again finds no room: a refusal naming the module, the scene unchanged
    with pytest.raises(RuntimeError, match="no 3x3 module at 10 mm pitch fits"):
        bpy.ops.skinsafe.cover_link(body="forearm_link")
    assert len(b2c.design_of(scene).modules) == len(design.modules)
    assert "no 3x3 module" in scene.skinsafe.error


def test_cover_link_needs_a_link(scene):
    assert bpy.ops.skinsafe.import_robot(source="panda") == {"FINISHED"}
    with pytest.raises(RuntimeError, match="cover: no link selected"):
        bpy.ops.skinsafe.cover_link(body="")

"""The Place Skin tool (addon/place_tool.py) driven by its operator with a given ray, as its modal part
does per mouse move: the preview on the link the ray meets is the module the click places (same taxels,
made active), the wheel's angle turns its rows, a spot where it cannot go gives the failing taxel on that
link and the reason, a ray past the robot says so and places nothing."""
import math

import bpy
import numpy as np
import pytest

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import place_tool

E = 0.13585 - 0.1197  # UR5 forearm capsule axis height (body frame), radius 0.04


@pytest.fixture
def scene():
    bpy.ops.wm.read_homefile(use_empty=True)
    b2c.clear_caches()
    bpy.ops.skinsafe.import_robot(source="ur5")
    s = bpy.context.scene.skinsafe.new_module
    s.rows, s.cols, s.pitch, s.taxel_diameter, s.margin = 8, 8, 0.01, 0.006, 0.002
    return bpy.context.scene


def _ray(body: str, point, normal, dist: float = 0.02):
    """A ray from `dist` m outside a body-frame surface point, pointing at it (world coordinates)."""
    W = np.array(b2c.body_objects(bpy.context.scene)[body].matrix_world)
    p, n = W[:3, :3] @ np.asarray(point) + W[:3, 3], W[:3, :3] @ np.asarray(normal, float)
    return tuple(p + dist * n), tuple(-n)


def test_the_preview_is_what_the_click_places_and_the_wheel_turns_the_rows(scene):
    origin, direction = _ray("forearm_link", (-0.25, 0.0, E + 0.04), (0, 0, 1))
    pv = place_tool.preview(scene, origin, direction)
    assert pv.reason == "" and pv.body == "forearm_link" and len(pv.world) == 64
    np.testing.assert_allclose(pv.anchor, (-0.25, 0.0, E + 0.04), atol=2e-3)  # the hit point on the capsule
    assert bpy.ops.skinsafe.place_skin(ray_origin=origin, ray_direction=direction) == {"FINISHED"}
    (obj,) = b2c.module_objects(scene)
    assert bpy.context.view_layer.objects.active is obj and obj.select_get()
    design = b2c.design_of(scene)
    W = np.array(b2c.body_objects(scene)["forearm_link"].matrix_world)
    np.testing.assert_allclose(design.taxels.positions @ W[:3, :3].T + W[:3, 3], pv.world, atol=1e-9)
    assert np.abs(design.taxels.frames[:, 0, 0]).min() > 0.99  # rows along the link's x axis

    # the wheel: a quarter turn places the rows around the link; the ray now meets the first module's
    # link elsewhere (12 cm along) so it does not overlap
    origin, direction = _ray("forearm_link", (-0.12, 0.0, E + 0.04), (0, 0, 1))
    turned = place_tool.preview(scene, origin, direction, angle=math.radians(90))
    assert turned.reason == ""
    assert bpy.ops.skinsafe.place_skin(ray_origin=origin, ray_direction=direction, angle=math.radians(90)) \
        == {"FINISHED"}
    t = b2c.design_of(scene).taxels
    new = t.module == bpy.context.view_layer.objects.active.skinsafe_module.module_id
    assert new.sum() == 64 and np.abs(t.frames[new, 0, 0]).max() < 0.05  # x now across the link


def test_a_misfit_shows_the_failing_taxel_and_the_reason_and_places_nothing(scene):
    origin, direction = _ray("forearm_link", (-0.25, 0.0, E + 0.04), (0, 0, 1))
    assert bpy.ops.skinsafe.place_skin(ray_origin=origin, ray_direction=direction) == {"FINISHED"}
    pv = place_tool.preview(scene, origin, direction)  # the same spot again: onto the first module
    assert pv.body == "forearm_link" and "overlaps module 0" in pv.reason and len(pv.world) == 0
    W = np.array(b2c.body_objects(scene)["forearm_link"].matrix_world)
    body_bad = np.linalg.inv(W) @ np.r_[pv.bad, 1.0]
    assert abs(np.hypot(body_bad[1], body_bad[2] - E) - 0.04) < 2e-3  # the red taxel lies on the forearm
    with pytest.raises(RuntimeError, match="overlaps module 0"):
        bpy.ops.skinsafe.place_skin(ray_origin=origin, ray_direction=direction)
    assert len(b2c.module_objects(scene)) == 1 and b2c.design_of(scene).n_taxels == 64
    far = place_tool.preview(scene, (5.0, 5.0, 5.0), (1.0, 0.0, 0.0))
    assert far.body is None and "meets no link" in far.reason
    with pytest.raises(RuntimeError, match="meets no link"):
        bpy.ops.skinsafe.place_skin(ray_origin=(5.0, 5.0, 5.0), ray_direction=(1.0, 0.0, 0.0))


def test_x_mirror_places_the_mirror_image_on_the_other_side(scene):
    s = scene.skinsafe.new_module
    s.rows, s.cols = 3, 4  # not square: a turned copy would not match
    assert bpy.ops.skinsafe.place_skin(ray_origin=(0.5, 0.0, 0.04), ray_direction=(-1.0, 0.0, 0.0),
                                       mirror_x=True) == {"FINISHED"}
    first, copy = sorted(b2c.module_objects(scene), key=lambda o: o.skinsafe_module.module_id)
    assert bpy.context.view_layer.objects.active is first and copy.select_get()
    assert not first.skinsafe_module.settings.mirrored and copy.skinsafe_module.settings.mirrored
    assert not s.mirrored  # the scene's settings as they were
    t = b2c.design_of(scene).taxels
    W = np.array(b2c.body_objects(scene)["base_link"].matrix_world)
    world = t.positions @ W[:3, :3].T + W[:3, 3]
    a, b = world[t.module == 0], world[t.module == 1]
    assert len(a) == len(b) == 12 and a[:, 0].min() > 0.05 and b[:, 0].max() < -0.05  # on either side
    np.testing.assert_allclose(b, a * [-1, 1, 1], atol=1e-3)  # taxel k of the copy: the mirror of taxel k

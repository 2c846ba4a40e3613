"""The Place Skin tool (addon/place_tool.py) driven by its operator with a given ray, as its modal part
does per mouse move: the preview on the link the ray meets is the module the click places (same taxels,
made active), the wheel's angle turns its rows, a spot where it cannot go gives the failing taxel on that
link and the reason, a ray past the robot says so and places nothing."""
import math
import re

import bpy
import numpy as np
import pytest

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import core_to_blender as c2b
from skinsafe.addon import place_tool

E = 0.13585 - 0.1197  # UR5 forearm capsule axis height (body frame), radius 0.04


@pytest.fixture(scope="module")
def robot():
    bpy.ops.wm.read_homefile(use_empty=True)
    b2c.clear_caches()
    bpy.ops.skinsafe.import_robot(source="ur5")


@pytest.fixture
def scene(robot):
    """The UR5 (imported once for the module) without a skin, the new-module settings 8x8 at 10 mm."""
    scene = bpy.context.scene
    c2b.clear_design(scene)
    scene.skinsafe.next_module_id = 0  # as in a new scene: no id retired yet
    s = scene.skinsafe.new_module
    s.rows, s.cols, s.pitch, s.taxel_diameter, s.margin, s.max_strain, s.mirrored = 8, 8, 0.01, 0.006, 0.002, 0.01, False
    return scene


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


def test_a_stretched_grid_is_refused_at_its_worst_pad_and_the_cut_that_fits_places(scene):
    """The forearm capsule's end is a sphere of radius 40 mm: an 8x8 FPC at 10 mm cannot wrap it."""
    from skinsafe.core.design.audit import module_strains

    origin, direction = _ray("forearm_link", (-0.40, 0.0, E), (-1, 0, 0))  # the cap's tip
    pv = place_tool.preview(scene, origin, direction)
    assert pv.kind == "strain" and "in-plane strain" in pv.reason and "over the FPC's 1.0%" in pv.reason
    assert len(pv.world) == 0 and pv.bad is not None
    W = np.array(b2c.body_objects(scene)["forearm_link"].matrix_world)
    body_bad = np.linalg.solve(W, np.r_[pv.bad, 1.0])[:3]
    assert abs(np.linalg.norm(body_bad - (-0.36, 0.0, E)) - 0.04) < 2e-3  # the red pad lies on the sphere
    head = place_tool.header(pv, False)
    assert head.startswith("stretched (red: the worst pad): ") and re.search(r"strain -?\d+\.\d% between taxels row", head)
    with pytest.raises(RuntimeError, match="in-plane strain"):
        bpy.ops.skinsafe.place_skin(ray_origin=origin, ray_direction=direction)
    assert not b2c.module_objects(scene)
    s = scene.skinsafe.new_module
    s.rows = s.cols = 4  # still stretched (2.4%): the message offers the cut that fits
    pv = place_tool.preview(scene, origin, direction)
    fit = re.search(r"a (\d)x(\d) module fits here", pv.reason)  # tried at that spot, not guessed
    assert pv.kind == "strain" and fit and 2 <= int(fit[1]) * int(fit[2]) < 16
    s.max_strain = 0.03  # an FPC that tolerates 3% takes the 4x4 there
    assert place_tool.preview(scene, origin, direction).reason == ""
    s.max_strain, s.rows, s.cols = 0.01, int(fit[1]), int(fit[2])  # the offered cut places
    assert bpy.ops.skinsafe.place_skin(ray_origin=origin, ray_direction=direction) == {"FINISHED"}
    (obj,) = b2c.module_objects(scene)
    design = b2c.design_of(scene)
    n = int(fit[1]) * int(fit[2])
    assert design.n_taxels == n and design.modules[0].max_strain == pytest.approx(0.01)  # the object's setting
    assert 0 < module_strains(design)[0][0] <= design.modules[0].max_strain
    obj.skinsafe_module.settings.max_strain = 0.001  # the module's own tolerance below its strain: named on it
    bpy.context.view_layer.update()
    assert "in-plane strain" in obj.skinsafe_module.error and b2c.design_of(scene).n_taxels == n

"""The Check panel (addon/findings.py): every finding of a check in the scene's list with the module and
place it names; Select makes that module active, Frame puts the 3D cursor on the named taxel (a stretched
module's worst pad); a passing skin empties the list; the coverage bars are the cells' union on the link."""
import re

import bpy
import numpy as np
import pytest

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import core_to_blender as c2b
from skinsafe.addon import findings

E = 0.13585 - 0.1197  # UR5 forearm capsule axis height (body frame), radius 0.04


@pytest.fixture(scope="module")
def scene():
    """UR5 with two 8x8 modules on the forearm, checked (shared: each test puts the design back)."""
    bpy.ops.wm.read_homefile(use_empty=True)
    b2c.clear_caches()
    bpy.ops.skinsafe.import_robot(source="ur5")
    assert len(findings.uncovered_world(bpy.context.scene)) == 0  # no design, no coverage report yet
    for x in (-0.3, -0.1):
        assert bpy.ops.skinsafe.place_module(body="forearm_link", anchor=(x, 0, E + 0.04), direction=(-1, 0, 0),
                                             use_cursor=False) == {"FINISHED"}
    assert bpy.ops.skinsafe.check(poses=2) == {"FINISHED"}
    return bpy.context.scene


def test_findings_list_select_and_frame(scene):
    assert len(scene.skinsafe_findings) == 0
    d = b2c.design_of(scene)
    lifted = d.with_taxels(d.taxels.subset(np.arange(d.n_taxels)))
    i = 64 + 10  # a taxel of the second module
    lifted.taxels.positions[i] += 0.005 * lifted.taxels.normals[i]  # 5 mm off the link: and its pads stretched
    c2b.store_design(scene, lifted)
    with pytest.raises(RuntimeError, match=r"3 problems, listed in Skin > Check"):
        bpy.ops.skinsafe.check(poses=2)
    f, stretched, unconfirmed = scene.skinsafe_findings
    # and the independent wrap of its flat pattern puts that pad 5 mm from where the map says
    assert "module 1 " in unconfirmed.text and re.search(r"independent wrap .* puts a pad [45]\.\d mm", unconfirmed.text)
    tid = int(b2c.design_of(scene).taxels.ids[i])
    assert f"taxel {tid} " in f.text and f.module_id == 1 and f.has_location
    # the stretched module (worst first), located at its worst pad: the lifted taxel's pair
    assert "module 1 " in stretched.text and "in-plane strain" in stretched.text and stretched.module_id == 1
    a, b = map(int, re.search(r"between taxels (\d+) and (\d+)", stretched.text).groups())
    assert tid in (a, b)  # the pair the lifted taxel is in
    W = np.array(b2c.body_objects(scene)["forearm_link"].matrix_world)
    k = np.flatnonzero(lifted.taxels.ids == a)[0]
    np.testing.assert_allclose(stretched.location, W[:3, :3] @ lifted.taxels.positions[k] + W[:3, 3], atol=1e-6)
    W = np.array(b2c.body_objects(scene)["forearm_link"].matrix_world)
    np.testing.assert_allclose(f.location, W[:3, :3] @ lifted.taxels.positions[i] + W[:3, 3], atol=1e-6)
    bpy.context.view_layer.objects.active = b2c.body_objects(scene)["forearm_link"]
    assert bpy.ops.skinsafe.show_finding(index=0) == {"FINISHED"}
    active = bpy.context.view_layer.objects.active
    assert active.skinsafe_module.module_id == 1 and active.select_get()
    assert bpy.ops.skinsafe.show_finding(index=0, frame=True) == {"FINISHED"}
    np.testing.assert_allclose(scene.cursor.location, f.location, atol=1e-6)
    c2b.store_design(scene, d)
    assert bpy.ops.skinsafe.check(poses=2) == {"FINISHED"} and len(scene.skinsafe_findings) == 0
    assert not bpy.ops.skinsafe.show_finding.poll()


def test_uncovered_overlay_points_are_off_every_module_and_a_covered_link_has_none(scene):
    from scipy.spatial import cKDTree

    from skinsafe.core.design.coverage import body_area, covered_area
    from skinsafe.core.design.surface import cached_surfaces

    d = b2c.design_of(scene)
    model = b2c.robot_for(scene).model
    r = d.coverage["forearm_link"]  # the bar's numbers: the cells' union on the link (Monte Carlo, seed fixed)
    assert r["skinned_area_m2"] == pytest.approx(covered_area(d, model, d.bodies.index("forearm_link")))
    assert r["fraction"] == pytest.approx(r["skinned_area_m2"] / body_area(model, "forearm_link"))
    assert findings.bar_text("forearm_link", r).startswith(f"forearm_link: {r['fraction']:.0%} covered (")
    W = np.array(b2c.body_objects(scene)["forearm_link"].matrix_world)
    taxels = d.taxels.positions @ W[:3, :3].T + W[:3, 3]  # both modules' taxels, world
    surface = cached_surfaces(b2c.robot_for(scene).model, ["forearm_link"])["forearm_link"].vertices
    pts = findings.uncovered_world(scene)
    # the forearm's bare part (world), each point farther than the modules' pitch (1 cm) from every taxel
    assert 0 < len(pts) < len(surface) and cKDTree(taxels).query(pts)[0].min() > d.modules[0].pitch
    assert cKDTree(surface @ W[:3, :3].T + W[:3, 3]).query(pts)[0].max() < 1e-9  # on the link's surface
    # the modules' own surroundings are not in it: the surface within 5 mm of a taxel holds no point
    near = (surface @ W[:3, :3].T + W[:3, 3])[cKDTree(taxels).query(surface @ W[:3, :3].T + W[:3, 3])[0] < 0.005]
    assert len(near) > 100 and cKDTree(pts).query(near)[0].min() > 0.005
    # a taxel on every vertex of the forearm's surface: the link is covered, the overlay has nothing on it
    idx = np.arange(len(surface)) % d.n_taxels
    cover = d.taxels.subset(idx)
    cover.positions[:] = surface
    c2b.store_design(scene, d.with_taxels(cover))
    assert len(findings.uncovered_world(scene)) == 0
    # the Check panel's toggle, and the draw handler added and removed cleanly (never added in background mode)
    scene.skinsafe_show_uncovered = True
    assert findings._overlay is None
    findings.overlay_on()
    handle = findings._overlay
    findings.overlay_on()
    assert handle is not None and findings._overlay is handle  # once
    findings.overlay_off()
    assert findings._overlay is None

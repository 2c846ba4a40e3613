"""The Check panel (addon/findings.py): every finding of a check in the scene's list with the module and
place it names; Select makes that module active, Frame puts the 3D cursor on the named taxel; a passing
skin empties the list."""
import bpy
import numpy as np
import pytest

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import core_to_blender as c2b

E = 0.13585 - 0.1197  # UR5 forearm capsule axis height (body frame), radius 0.04


def test_findings_list_select_and_frame():
    bpy.ops.wm.read_homefile(use_empty=True)
    b2c.clear_caches()
    scene = bpy.context.scene
    bpy.ops.skinsafe.import_robot(source="ur5")
    for x in (-0.3, -0.1):
        assert bpy.ops.skinsafe.place_module(body="forearm_link", anchor=(x, 0, E + 0.04), direction=(-1, 0, 0),
                                             use_cursor=False) == {"FINISHED"}
    assert bpy.ops.skinsafe.check(poses=2) == {"FINISHED"} and len(scene.skinsafe_findings) == 0
    d = b2c.design_of(scene)
    lifted = d.with_taxels(d.taxels.subset(np.arange(d.n_taxels)))
    i = 64 + 10  # a taxel of the second module
    lifted.taxels.positions[i] += 0.005 * lifted.taxels.normals[i]  # 5 mm off the link
    c2b.store_design(scene, lifted)
    with pytest.raises(RuntimeError, match=r"1 problems, listed in Skin > Check"):
        bpy.ops.skinsafe.check(poses=2)
    (f,) = scene.skinsafe_findings
    tid = int(b2c.design_of(scene).taxels.ids[i])
    assert f"taxel {tid} " in f.text and f.module_id == 1 and f.has_location
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

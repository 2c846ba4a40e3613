"""The PFL heat map operator through bpy.ops, headless: per-taxel v_max on the module meshes."""
import bpy
import numpy as np

from skinsafe.addon import blender_to_core as b2c
from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.safety import pfl

E = 0.13585 - 0.1197  # UR5 forearm capsule axis height (body frame)


def test_pfl_heat_map_matches_core(tmp_path):
    bpy.ops.wm.read_homefile(use_empty=True)
    b2c.clear_caches()
    scene = bpy.context.scene
    assert not bpy.ops.skinsafe.map_pfl.poll()  # no skin yet
    bpy.ops.skinsafe.import_robot(source="ur5")
    s = scene.skinsafe.new_module
    for k, v in {"template": "rect", "rows": 6, "cols": 6, "pitch": 0.01, "taxel_diameter": 0.006, "margin": 0.002,
                 "min_bend_radius": 0.01, "method": "geodesic"}.items():
        setattr(s, k, v)
    assert bpy.ops.skinsafe.place_module(body="forearm_link", anchor=(-0.2, 0, E + 0.05), direction=(-1, 0, 0),
                                         use_cursor=False) == {"FINISHED"}
    assert bpy.ops.skinsafe.map_pfl(region="chest") == {"FINISHED"}
    design = b2c.design_of(scene)
    robot = build_ur5()
    kin = TaxelKinematics(robot.model, design)
    want = pfl.v_max("chest", 1 / pfl.effective_mass(kin, robot.home))
    obj = next(o for o in scene.objects if o.skinsafe_module.is_module)
    got = np.empty(len(obj.data.polygons), dtype=np.float32)
    obj.data.attributes["pfl_vmax"].data.foreach_get("value", got)
    assert np.allclose(got, want, rtol=1e-5)
    # chest (40 kg, 25 N/mm, 280 N): at most 280 / sqrt(40 * 25e3) = 0.28 m/s plus the robot's share
    assert want.min() >= 0.28 - 1e-9 and "safe approach speed" in scene.skinsafe.message

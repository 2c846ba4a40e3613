"""xacro arguments through the add-on: the import operator's 'xacro arguments' property, kept in the
scene so the robot loads again; a missing argument is refused naming it, the scene left as it was."""
import bpy
import pytest

from skinsafe.addon import blender_to_core as b2c
from skinsafe.core.robot.catalog import description


def test_import_gen3_with_and_without_its_dof_argument():
    gen3 = description("gen3")
    bpy.ops.wm.read_homefile(use_empty=True)
    b2c.clear_caches()
    with pytest.raises(RuntimeError, match=r"'dof' in the missing path is built from an argument left empty"):
        bpy.ops.skinsafe.import_robot(source="FILE", filepath=gen3.path, package_dirs=gen3.package_dirs[0])
    assert not bpy.context.scene.skinsafe.robot_kind  # refused before the scene changed
    with pytest.raises(RuntimeError, match="'dof7' is not NAME:=VALUE"):
        bpy.ops.skinsafe.import_robot(source="FILE", filepath=gen3.path, package_dirs=gen3.package_dirs[0],
                                      xacro_args="dof7")
    assert bpy.ops.skinsafe.import_robot(source="FILE", filepath=gen3.path, package_dirs=gen3.package_dirs[0],
                                         xacro_args="dof:=7; vision:=false") == {"FINISHED"}
    scene = bpy.context.scene
    assert scene.skinsafe.robot_xacro_args == "dof:=7;vision:=false"
    assert "forearm_link" in b2c.body_objects(scene)
    b2c.clear_caches()  # the robot loads again from the scene's own record, arguments included
    assert b2c.robot_ref(scene).xacro_args == {"dof": "7", "vision": "false"}
    assert b2c.robot_for(scene).model.njnt == 7

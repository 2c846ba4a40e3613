"""Long work off Blender's thread (addon/background.py): a robot file read in a worker thread lands in the
cache the scene's import then builds from; its refusal comes back as the exception, for the operator to
report; the import operator headless (`bpy.app.background`: no event loop) runs the same job and waits. A
check or a link's cover run in a worker is kept only for the skin it ran on: a module moved meanwhile refuses
its report or its new modules."""
import threading

import bpy
import pytest

from skinsafe.addon import background, cover, designer
from skinsafe.addon import blender_to_core as b2c
from skinsafe.core.robot.catalog import description
from skinsafe.core.skin.model import DesignError, RobotRef


def test_a_robot_file_loads_in_a_worker_thread_and_its_refusal_comes_back():
    gen3 = description("gen3")
    ref = RobotRef("urdf", "gen3", gen3.path, (gen3.package_dirs[0],), {"dof": "7", "vision": "false"})
    b2c.clear_caches()
    job = background.Job(lambda r: (threading.get_ident(), b2c.preload(r)), ref)
    assert job.wait(300) and job.error is None
    worker, robot = job.result
    assert worker != threading.get_ident() and robot.model.njnt == 7
    assert b2c.preload(ref) is robot  # cached: the import builds the scene from it without reading again
    bad = background.Job(b2c.preload, RobotRef("urdf", "nope", "/nonexistent/nope.urdf"))
    assert bad.wait(60) and bad.result is None and isinstance(bad.error, DesignError)
    assert "nope.urdf" in str(bad.error)
    bpy.ops.wm.read_homefile(use_empty=True)
    with pytest.raises(RuntimeError, match="nope.urdf"):
        bpy.ops.skinsafe.import_robot(source="FILE", filepath="/nonexistent/nope.urdf")
    assert not bpy.context.scene.skinsafe.robot_kind  # refused before the scene changed


def test_a_check_run_off_the_thread_is_not_kept_for_a_skin_edited_meanwhile():
    bpy.ops.wm.read_homefile(use_empty=True)
    b2c.clear_caches()
    scene = bpy.context.scene
    bpy.ops.skinsafe.import_robot(source="ur5")
    bpy.ops.skinsafe.place_module(body="forearm_link", anchor=(-0.25, 0, 0.13585 - 0.1197 + 0.04),
                                  direction=(-1, 0, 0), use_cursor=False)
    rev = scene.skinsafe.design_rev
    job = background.Job(designer.check_work, designer.need_design(scene), b2c.robot_for(scene), 2)
    b2c.module_objects(scene)[0].location.x -= 0.02  # the designer moves the module while it runs
    bpy.context.view_layer.update()
    assert job.wait(120) and job.error is None and job.result[0] == []
    with pytest.raises(DesignError, match="changed while it was being checked; run Check again"):
        designer.keep_check(scene, rev, job.result)
    assert b2c.design_of(scene).coverage == {}  # the report of the old skin is not kept
    rev = scene.skinsafe.design_rev
    job = background.Job(designer.check_work, designer.need_design(scene), b2c.robot_for(scene), 2)
    assert job.wait(120) and designer.keep_check(scene, rev, job.result) == []
    assert b2c.design_of(scene).coverage["forearm_link"]["taxels"] == 64


def test_a_cover_run_off_the_thread_makes_its_objects_only_for_the_skin_it_covered():
    bpy.ops.wm.read_homefile(use_empty=True)
    b2c.clear_caches()
    scene = bpy.context.scene
    bpy.ops.skinsafe.import_robot(source="ur5")
    s = scene.skinsafe.new_module
    s.rows, s.cols, s.pitch, s.taxel_diameter, s.margin = 3, 3, 0.01, 0.006, 0.001
    bpy.ops.skinsafe.place_module(body="forearm_link", anchor=(-0.2, 0, 0.13585 - 0.1197 + 0.04),
                                  direction=(-1, 0, 0), use_cursor=False)
    rev = scene.skinsafe.design_rev
    job = background.Job(cover.cover_work, *cover.cover_inputs(scene, "forearm_link"))
    b2c.module_objects(scene)[0].location.x -= 0.02  # moved while the fill runs
    bpy.context.view_layer.update()
    assert job.wait(300) and job.error is None
    with pytest.raises(DesignError, match="changed while the link was being covered; run Cover again"):
        cover.keep_cover(scene, "forearm_link", rev, job.result)
    assert len(b2c.module_objects(scene)) == 1  # no objects for a fill of the old skin
    rev = scene.skinsafe.design_rev
    job = background.Job(cover.cover_work, *cover.cover_inputs(scene, "forearm_link"))
    assert job.wait(300)
    objects, row = cover.keep_cover(scene, "forearm_link", rev, job.result)
    assert len(objects) == len(job.result.modules) - 1 > 5 and row["overlaps"] == 0
    assert len(b2c.module_objects(scene)) == len(b2c.design_of(scene).modules)

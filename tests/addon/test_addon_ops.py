"""The Blender add-on through bpy.ops, headless: import, pose, place, re-generate, refusals,
Jacobian heat map, boards, coverage, export and .blend round trip."""
import json

import bpy
import mujoco
import numpy as np
import pytest
from mathutils import Vector
from mathutils.bvhtree import BVHTree

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import core_to_blender as c2b
from skinsafe.core.robot.kinematics import TaxelKinematics, retractability
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.skin import taxel_map

E = 0.13585 - 0.1197  # UR5 forearm capsule axis height (body frame), radius 0.04


@pytest.fixture
def scene():
    bpy.ops.wm.read_homefile(use_empty=True)
    b2c.clear_caches()
    return bpy.context.scene


def _place(body, anchor, direction=(-1, 0, 0), **settings):
    s = bpy.context.scene.skinsafe.new_module
    for k, v in {"template": "rect", "rows": 8, "cols": 8, "pitch": 0.01, "taxel_diameter": 0.006, "margin": 0.002,
                 "min_bend_radius": 0.01, "method": "geodesic", **settings}.items():
        setattr(s, k, v)
    return bpy.ops.skinsafe.place_module(body=body, anchor=anchor, direction=direction, use_cursor=False)


def _modules(scene):
    return sorted(b2c.module_objects(scene), key=lambda o: o.skinsafe_module.module_id)


def _body_bvh(obj):
    me = obj.data
    co = [v.co.copy() for v in me.vertices]
    return BVHTree.FromPolygons(co, [tuple(p.vertices) for p in me.polygons])


def test_import_builtin_robots_and_pose(scene):
    assert bpy.ops.skinsafe.import_robot(source="panda") == {"FINISHED"}
    assert len(scene.skinsafe.joints) == 7
    assert bpy.ops.skinsafe.import_robot(source="ur5") == {"FINISHED"}
    bodies = b2c.body_objects(scene)
    assert "link3" not in bodies and len(scene.skinsafe.joints) == 6  # the Panda was replaced
    assert bodies["forearm_link"].parent is bodies["upper_arm_link"]
    assert bodies["forearm_link"]["joint_name"] == "elbow_joint"
    assert list(bodies["forearm_link"]["joint_axis"]) == [0.0, 0.0, 1.0]
    q = np.array([0.3, -1.0, 1.2, -0.5, 0.7, 0.2])
    for name, v in zip([j.name for j in scene.skinsafe.joints], q):
        bpy.ops.skinsafe.set_pose(preset="JOINT", joint=name, value=v)
    bpy.context.view_layer.update()
    m = build_ur5().model
    d = mujoco.MjData(m)
    d.qpos[:] = q
    mujoco.mj_kinematics(m, d)
    for name in ("wrist_3_link", "forearm_link"):
        W = np.array(bodies[name].matrix_world)
        assert np.allclose(W[:3, 3], d.xpos[m.body(name).id], atol=1e-5)
        assert np.allclose(W[:3, :3], d.xmat[m.body(name).id].reshape(3, 3), atol=1e-5)
    with pytest.raises(RuntimeError, match="joint 'nope' is unknown"):
        bpy.ops.skinsafe.set_pose(preset="JOINT", joint="nope", value=0)


def test_place_frames_surface_regenerate_and_refusals(scene):
    bpy.ops.skinsafe.import_robot(source="ur5")
    assert _place("forearm_link", (-0.2, 0, E + 0.05)) == {"FINISHED"}
    (obj,) = _modules(scene)
    design = b2c.design_of(scene)
    assert design.n_taxels == 64 and len(obj.data.polygons) == 64
    F = design.taxels.frames
    assert np.abs(np.einsum("nji,njk->nik", F, F) - np.eye(3)).max() < 1e-9
    assert np.allclose(np.linalg.det(F), 1.0)
    # taxel centres lie on the link's Blender mesh within 0.5 mm; z agrees with the mesh normal
    body = b2c.body_objects(scene)["forearm_link"]
    bvh = _body_bvh(body)
    for p, z in zip(design.taxels.positions, F[:, :, 2]):
        loc, normal, _, dist = bvh.find_nearest(Vector(p))
        assert dist < 5e-4
        assert np.dot(z, normal) > np.cos(np.radians(5))
        assert np.dot(z, [0, p[1], p[2] - E]) > 0  # outward
    bpy.context.view_layer.update()
    world = c2b.module_taxel_centres(obj)
    W = np.array(body.matrix_world)
    assert np.allclose(world, design.taxels.positions @ W[:3, :3].T + W[:3, 3], atol=2e-4)  # mesh = design

    # move: the depsgraph handler re-generates; so does the operator (step by step, no event loop)
    before = design.taxels.positions.copy()
    obj.location.x -= 0.05
    bpy.context.view_layer.update()
    after = b2c.design_of(scene).taxels.positions
    assert np.allclose(after, before + [-0.05, 0, 0], atol=1e-6)
    scene.skinsafe.auto_regenerate = False
    obj.rotation_euler.rotate_axis("Z", np.pi / 2)  # rows now around the link
    bpy.context.view_layer.update()
    assert np.allclose(b2c.design_of(scene).taxels.positions, after)
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.skinsafe.regenerate() == {"FINISHED"}
    F2 = b2c.design_of(scene).taxels.frames
    assert np.abs(F2[:, 0, 0]).max() < 1e-3  # x is no longer along the axis
    obj.scale = (2.0, 1.0, 1.0)  # resize: twice the columns
    assert bpy.ops.skinsafe.regenerate() == {"FINISHED"}
    assert b2c.design_of(scene).n_taxels == 128 and obj.skinsafe_module.settings.cols == 16
    # float32 round-off in a placed module's scale is no resize: the heat map stays, nothing re-generates
    scene.skinsafe.auto_regenerate = True
    obj.scale = (1.0, 0.99999994, 0.99999994)
    obj.skinsafe_module.placed_matrix = b2c.matrix_key(obj)
    mesh = obj.data.name
    bpy.context.view_layer.update()
    assert obj.data.name == mesh and b2c.design_of(scene).n_taxels == 128

    with pytest.raises(RuntimeError, match="overlaps module 0"):
        _place("forearm_link", (-0.25, 0, E + 0.05))
    assert "overlaps" in scene.skinsafe.error
    with pytest.raises(RuntimeError, match=r"bend radius (39\.9|40\.\d) mm .* below the FPC's minimum 60\.0 mm"):
        _place("forearm_link", (-0.1, 0, E - 0.05), min_bend_radius=0.06)
    with pytest.raises(RuntimeError, match="falls off the surface of 'wrist_3_link'"):
        _place("wrist_3_link", (0.04, 0, 0.03), direction=(0, 0, 1), rows=4, cols=16, pitch=0.005,
               taxel_diameter=0.003, margin=0.001)
    assert b2c.design_of(scene).n_taxels == 128  # refusals leave the design as it was


def test_jacobian_map_boards_coverage_export_and_blend_round_trip(scene, tmp_path):
    bpy.ops.skinsafe.import_robot(source="ur5")
    _place("forearm_link", (-0.1, 0, E + 0.05))
    _place("forearm_link", (-0.25, 0, E + 0.05))
    _place("upper_arm_link", (-0.2, 0, 0.13585 + 0.06))
    bpy.ops.skinsafe.set_pose(preset="JOINT", joint="shoulder_lift_joint", value=-0.4)
    assert bpy.ops.skinsafe.map_jacobians() == {"FINISHED"}
    design = b2c.design_of(scene)
    robot = build_ur5()
    q = robot.home.copy()
    q[1] = -0.4
    J, _, frames = TaxelKinematics(robot.model, design).jacobians(q)
    want = retractability(J, frames)
    for obj in _modules(scene):
        on = design.taxels.module == obj.skinsafe_module.module_id
        got = np.empty(int(on.sum()), dtype=np.float32)
        obj.data.attributes["retractability"].data.foreach_get("value", got)
        assert np.allclose(got, want[on], rtol=1e-5)
    assert want.min() > 0.1 and want.max() < 1.5

    scene.skinsafe.board_capacity = 64
    assert bpy.ops.skinsafe.assign_boards() == {"FINISHED"}
    assert len(b2c.design_of(scene).boards) == 3
    scene.skinsafe.board_capacity = 32
    with pytest.raises(RuntimeError, match="64 taxels exceed a board's 32 channels"):
        bpy.ops.skinsafe.assign_boards()
    assert bpy.ops.skinsafe.coverage() == {"FINISHED"}
    assert b2c.design_of(scene).coverage["forearm_link"]["taxels"] == 128
    out = tmp_path / "skin.json"
    assert bpy.ops.skinsafe.export_taxel_map(filepath=str(out)) == {"FINISHED"}
    saved = taxel_map.load(out)
    assert saved.n_taxels == 192 and len(saved.boards) == 3
    assert bpy.ops.skinsafe.export_mjcf(directory=str(tmp_path / "scene")) == {"FINISHED"}
    m = mujoco.MjModel.from_xml_path(str(tmp_path / "scene" / "scene.xml"))
    assert m.nbody >= 7 and taxel_map.load(tmp_path / "scene" / "taxel_map.json").n_taxels == 192

    blend = tmp_path / "skin.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.read_homefile(use_empty=True)
    assert b2c.design_of(bpy.context.scene) is None
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    scene = bpy.context.scene
    back = b2c.design_of(scene)
    assert np.array_equal(back.taxels.positions, saved.taxels.positions)
    assert np.array_equal(back.taxels.frames, saved.taxels.frames)
    assert len(_modules(scene)) == 3 and scene.skinsafe.robot_name == "ur5"
    assert json.loads(bpy.data.texts[b2c.TEXT_NAME].as_string())["schema_version"] == 1

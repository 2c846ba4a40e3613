"""The add-on with robot files written here (URDF with primitives and an OBJ mesh) and the bundled
ROS description (the built extension zip in a clean Blender: test_clean_install.py)."""
import json
import textwrap
from pathlib import Path

import bpy
import numpy as np
import pytest

from skinsafe.addon import blender_to_core as b2c
from skinsafe.core.skin.ids import stable_ids

ROOT = Path(__file__).resolve().parents[2]
INERTIA = '<inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial>'


def _prism_obj(path: Path, w=0.06, h=0.3):
    """An OBJ hexagonal prism (radius w, length h along z), outward faces."""
    ang = np.arange(6) * np.pi / 3
    ring = np.stack([w * np.cos(ang), w * np.sin(ang)], 1)
    v = [(x, y, 0.0) for x, y in ring] + [(x, y, h) for x, y in ring]
    f = [(i, (i + 1) % 6, 6 + (i + 1) % 6, 6 + i) for i in range(6)] + [tuple(range(5, -1, -1)), tuple(range(6, 12))]
    path.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in v) + "".join(
        "f " + " ".join(str(i + 1) for i in face) + "\n" for face in f))


def _urdf(tmp: Path, mesh="prism.obj", joint="revolute") -> Path:
    path = tmp / "bot.urdf"
    path.write_text(textwrap.dedent(f"""\
        <robot name="bot">
          <link name="base"><collision><geometry><box size="0.2 0.2 0.1"/></geometry></collision>{INERTIA}</link>
          <link name="arm"><collision><origin xyz="0 0 0.2"/><geometry><cylinder radius="0.05" length="0.3"/></geometry>
            </collision>{INERTIA}</link>
          <link name="hand"><collision><geometry><mesh filename="{mesh}"/></geometry></collision>{INERTIA}</link>
          <joint name="j1" type="{joint}"><parent link="base"/><child link="arm"/><origin xyz="0 0 0.05"/>
            <axis xyz="0 0 1"/><limit lower="-2" upper="2" effort="1" velocity="1.5"/></joint>
          <joint name="j2" type="revolute"><parent link="arm"/><child link="hand"/><origin xyz="0 0 0.4"/>
            <axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="1" velocity="1.5"/></joint>
        </robot>"""))
    return path


def test_urdf_import_place_on_mesh_and_refusals(tmp_path):
    bpy.ops.wm.read_homefile(use_empty=True)
    _prism_obj(tmp_path / "prism.obj")
    path = _urdf(tmp_path)
    assert bpy.ops.skinsafe.import_robot(source="FILE", filepath=str(path)) == {"FINISHED"}
    scene = bpy.context.scene
    bodies = b2c.body_objects(scene)
    assert {"base", "arm", "hand"} <= set(bodies) and bodies["hand"].parent is bodies["arm"]
    assert list(bodies["hand"]["joint_axis"]) == [0.0, 1.0, 0.0] and list(bodies["hand"]["joint_range"]) == [-1, 1]
    s = scene.skinsafe.new_module
    s.rows, s.cols, s.pitch, s.taxel_diameter, s.margin, s.min_bend_radius = 4, 6, 0.008, 0.004, 0.001, 0.005
    # on the mesh link: a flat face of the prism (outward normal +x rotated by 30 deg: face 0 between corners 0, 1)
    n = np.array([np.cos(np.pi / 6), np.sin(np.pi / 6), 0])
    anchor = 0.06 * np.cos(np.pi / 6) * n + [0, 0, 0.15] + 0.01 * n
    assert bpy.ops.skinsafe.place_module(body="hand", anchor=anchor, direction=(0, 0, 1), use_cursor=False) == {"FINISHED"}
    d = b2c.design_of(scene)
    assert d.n_taxels == 24
    assert np.allclose(d.taxels.frames[:, :, 2], n, atol=1e-6)  # flat face: z = its normal
    assert np.allclose(d.taxels.positions @ n, 0.06 * np.cos(np.pi / 6), atol=1e-6)
    assert np.allclose(np.ptp(d.taxels.positions[:, 2]), 5 * 0.008)  # rows along z, 6 columns
    # a cylinder link from a URDF primitive
    assert bpy.ops.skinsafe.place_module(body="arm", anchor=(0.06, 0, 0.2), direction=(0, 0, 1),
                                         use_cursor=False) == {"FINISHED"}
    p = b2c.design_of(scene).taxels.positions[24:]
    assert np.abs(np.hypot(p[:, 0], p[:, 1]) - 0.05).max() < 5e-4

    bad = _urdf(tmp_path, mesh="gone.obj")
    with pytest.raises(RuntimeError, match="link 'hand' collision #0: mesh file 'gone.obj' not found"):
        bpy.ops.skinsafe.import_robot(source="FILE", filepath=str(bad))
    bad = _urdf(tmp_path, joint="planar")
    with pytest.raises(RuntimeError, match="joint 'j1' has type 'planar'"):
        bpy.ops.skinsafe.import_robot(source="FILE", filepath=str(bad))
    assert b2c.design_of(scene).n_taxels == 48  # refused imports leave the scene as it was


def test_ros_description_with_collada_visuals_through_the_operators(tmp_path):
    """The bundled Franka xacro (package://, DAE visuals Blender 5 cannot import itself): the core
    reads the meshes, Blender gets each link's budgeted visual surface, a module goes on a link."""
    asset = ROOT / "blend_assets" / "franka_description"
    bpy.ops.wm.read_homefile(use_empty=True)
    assert bpy.ops.skinsafe.import_robot(source="FILE", filepath=str(asset / "robots/panda/panda.urdf.xacro"),
                                         package_dirs=str(asset)) == {"FINISHED"}
    scene = bpy.context.scene
    bodies = b2c.body_objects(scene)
    link4 = bodies["panda_link4"]
    assert 10000 < len(link4.data.polygons) <= 20000  # the real DAE visual (14,620 faces), not a hull or a box
    assert len(scene.skinsafe.joints) == 7 and scene.skinsafe.robot_package_dirs == str(asset)
    s = scene.skinsafe.new_module
    s.rows, s.cols, s.pitch, s.taxel_diameter, s.margin, s.min_bend_radius = 3, 3, 0.012, 0.007, 0.002, 0.02
    surf = b2c.surface_of(link4)
    from skinsafe.core.design.layout import tile_body
    from skinsafe.core.skin.model import Module

    template = Module(0, "t", "panda_link4", rows=3, cols=3, pitch=0.012, taxel_diameter=0.007, min_bend_radius=0.02)
    first = tile_body(surf, b2c.robot_for(scene).model, template, "panda_link4", 0, limit=9)[0][0]
    assert bpy.ops.skinsafe.place_module(body="panda_link4", anchor=first.origin, direction=first.origin_frame[:, 0],
                                         use_cursor=False) == {"FINISHED"}
    d = b2c.design_of(scene)
    assert d.n_taxels == 9
    assert surf.closest(d.taxels.positions)[3].max() < 1e-6  # on the visual surface
    # checked through the operator as `skinsafe check` does (validation, audit, coverage)
    assert bpy.ops.skinsafe.check(poses=4) == {"FINISHED"}
    assert "valid" in scene.skinsafe.message and "panda_link4" in scene.skinsafe.coverage_text
    from skinsafe.addon import core_to_blender as c2b

    lifted = d.with_taxels(d.taxels.subset(np.arange(d.n_taxels)))
    lifted.taxels.positions[4] += 0.005 * lifted.taxels.normals[4]  # one taxel 5 mm off the link
    c2b.store_design(scene, lifted)
    with pytest.raises(RuntimeError, match=r"taxel \d+ on 'panda_link4' is 5.0 mm off the link's surface"):
        bpy.ops.skinsafe.check(poses=4)
    c2b.store_design(scene, d)
    # exported through the operator: the contact surface is where the skin is, no self contact at home
    import mujoco

    from skinsafe.core.bench.robot_import import self_contacts
    from skinsafe.core.sim.skin_collision import taxel_clearance

    out = tmp_path / "scene"
    assert bpy.ops.skinsafe.export_mjcf(directory=str(out)) == {"FINISHED"}
    spec = mujoco.MjSpec.from_file(str(out / "scene.xml"))
    home = b2c.robot_for(scene).home
    assert np.abs(taxel_clearance(spec, d, home)).max() <= 1e-3
    model = spec.compile()
    data = mujoco.MjData(model)
    data.qpos[:] = home
    mujoco.mj_forward(model, data)
    assert self_contacts(model, data) == 0
    with pytest.raises(RuntimeError, match="package 'franka_description'|find franka_description"):
        bpy.ops.skinsafe.import_robot(source="FILE", filepath=str(asset / "robots/panda/panda.urdf.xacro"))


def test_sample_blend_asset_holds_a_full_skin():
    path = ROOT / "blend_assets" / "ur5_skin.blend"
    if not path.exists():
        pytest.skip("blend_assets/ur5_skin.blend not built; run blend_assets/build_sample.py")
    bpy.ops.wm.open_mainfile(filepath=str(path))
    scene = bpy.context.scene
    d = b2c.design_of(scene)
    assert d.n_taxels >= 1500 and len(d.boards) >= 2
    assert {"upper_arm_link", "forearm_link", "wrist_1_link"} <= {m.body for m in d.modules}
    assert sum(len(o.data.polygons) for o in b2c.module_objects(scene)) == d.n_taxels
    # saved under the current rules: stable taxel ids as stored (nothing converted on load), the robot's links kept
    assert "older taxel-id rule" not in scene.skinsafe.message
    assert json.loads(bpy.data.texts[b2c.TEXT_NAME].as_string())["taxels"]["ids"] == stable_ids(d.taxels.module).tolist()
    assert {it.body for it in scene.skinsafe.links} == set(b2c.robot_for(scene).body_names)
    for m in d.modules:  # each module on one board, within capacity
        assert set(d.taxels.board[d.taxels.module == m.id].tolist()) == {m.board}
    # its first edit (a module deleted) renumbers no other module's taxels; the deleted id is retired
    gone = d.modules[0]
    for o in scene.objects:
        o.select_set(o.skinsafe_module.module_id == gone.id)
    assert bpy.ops.object.delete() == {"FINISHED"}
    bpy.context.view_layer.update()
    after = b2c.design_of(scene)
    keep = d.taxels.module != gone.id
    assert np.array_equal(after.taxels.ids, d.taxels.ids[keep]) and gone.id in after.retired_modules

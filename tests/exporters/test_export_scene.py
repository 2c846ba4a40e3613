"""Export: UR5 and Panda sample skins to MJCF loaded by plain MuJoCo; mesh robots; errors write nothing."""
import mujoco
import numpy as np
import pytest
import trimesh

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.models import build_panda, build_ur5, load_robot
from skinsafe.core.sim.scene import Obstacle, SceneOptions, build_scene
from skinsafe.core.skin import taxel_map
from skinsafe.core.skin.model import Board, DesignError, Module, RobotRef, SkinDesign, Taxels, frames_from_normals
from skinsafe.exporters.mjcf import export_scene


@pytest.fixture(scope="module")
def ur5_design():
    return make_sample_design("ur5", pitch=0.01)


@pytest.mark.parametrize("name", ["ur5", "panda"])
def test_export_loads_with_plain_mujoco_and_sites_match_taxels(tmp_path, name):
    design = make_sample_design(name, pitch=0.01)
    robot = build_ur5() if name == "ur5" else build_panda()
    scene = export_scene(design, robot, tmp_path / "out", [Obstacle("probe", "sphere", (0.01,), mocap=True)])
    assert sorted(p.name for p in scene.parent.iterdir()) == ["scene.xml", "taxel_map.json"]
    model = mujoco.MjModel.from_xml_path(str(scene))
    t = design.taxels
    assert model.nmocap == 1
    for i in [0, len(t) // 2, len(t) - 1]:
        sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, f"taxel_{int(t.ids[i])}")
        assert model.body(model.site_bodyid[sid]).name == design.body_of(i)
        np.testing.assert_allclose(model.site_pos[sid], t.positions[i], atol=1e-6)
        R = np.zeros(9)
        mujoco.mju_quat2Mat(R, model.site_quat[sid])
        np.testing.assert_allclose(R.reshape(3, 3), t.frames[i], atol=1e-5)
    back = taxel_map.load(scene.parent / "taxel_map.json")
    np.testing.assert_array_equal(back.taxels.ids, t.ids)
    assert robot.model.nsite == build_ur5().model.nsite if name == "ur5" else True  # robot.spec left as it was


def test_touch_sensors_one_per_taxel(ur5_design):
    model = build_scene(ur5_design, build_ur5(), options=SceneOptions(touch_sensors=True)).compile()
    assert model.nsensor == ur5_design.n_taxels
    assert (model.sensor_type == mujoco.mjtSensor.mjSENS_TOUCH).all()


def test_unknown_body_fails_naming_it_and_writes_nothing(tmp_path, ur5_design):
    bad = SkinDesign(ur5_design.robot, ["upper_arm_link", "tentacle_link", "wrist_1_link", "wrist_2_link",
                                        "wrist_3_link"], ur5_design.modules, ur5_design.boards, ur5_design.taxels)
    with pytest.raises(DesignError, match="tentacle_link"):
        export_scene(bad, build_ur5(), tmp_path / "out")
    assert list(tmp_path.iterdir()) == []


def test_bad_obstacle_fails_and_writes_nothing(tmp_path, ur5_design):
    with pytest.raises(DesignError, match="obstacle #0 'ball'.*size"):
        export_scene(ur5_design, build_ur5(), tmp_path / "out", [Obstacle("ball", "sphere", (0.1, 0.2))])
    with pytest.raises(DesignError, match="'table'.*already used"):
        export_scene(ur5_design, build_ur5(), tmp_path / "out", [Obstacle("table", "sphere", (0.1,))])
    assert list(tmp_path.iterdir()) == []


# --- a mesh robot --------------------------------------------------------------------------

def _mesh_robot(folder, mesh):
    """One hinged link whose collision and visual geometry is `mesh` (written as link.stl)."""
    (folder / "link.stl").write_bytes(mesh) if isinstance(mesh, bytes) else mesh.export(str(folder / "link.stl"))
    (folder / "robot.xml").write_text("""<mujoco model="meshbot"><compiler meshdir="."/>
  <asset><mesh name="link" file="link.stl"/></asset>
  <worldbody><body name="arm" pos="0 0 0.5"><joint name="j" type="hinge" axis="0 0 1"/>
    <geom name="arm_col" type="mesh" mesh="link"/>
    <geom name="arm_vis" type="mesh" mesh="link" contype="0" conaffinity="0" group="1"/>
  </body><geom name="far_box" type="box" size="0.1 0.1 0.1" pos="5 0 0"/></worldbody></mujoco>""")
    return load_robot(RobotRef("mjcf", "robot", str(folder / "robot.xml")))


def _skin_on(body="arm", n=4):
    normals = np.tile([0.0, 0.0, 1.0], (n, 1))
    taxels = Taxels(ids=np.arange(n, dtype=np.int64), body=np.zeros(n, np.int32),
                    positions=np.c_[np.linspace(-0.1, 0.1, n), np.zeros(n), np.full(n, 0.04)],
                    frames=frames_from_normals(normals, np.array([1.0, 0, 0])), module=np.zeros(n, np.int32),
                    board=np.zeros(n, np.int32), channel=np.arange(n, dtype=np.int32), area=np.full(n, 3e-5),
                    enabled=np.ones(n, bool), thresholds={"force": np.full(n, 5.0)})
    return SkinDesign(RobotRef("mjcf", "robot", "robot.xml"), [body], [Module(0, "m", body, pitch=0.05)],
                      [Board(0, "b", 1)], taxels)


def _capsule():
    return trimesh.creation.capsule(height=0.3, radius=0.04, count=[48, 48]).apply_transform(
        trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))


@pytest.mark.parametrize("mode", ["full", "hull", "decimate", "primitive"])
def test_mesh_robot_collision_modes(tmp_path, mode):
    robot = _mesh_robot(tmp_path, _capsule())
    out = export_scene(_skin_on(), robot, tmp_path / "out", options=SceneOptions(collision=mode, target_faces=200))
    model = mujoco.MjModel.from_xml_path(str(out))  # meshes found relative to scene.xml
    col = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "arm_col")
    full_faces = len(_capsule().faces)
    if mode == "primitive":
        assert model.geom_type[col] == mujoco.mjtGeom.mjGEOM_CAPSULE
        np.testing.assert_allclose(model.geom_size[col][:2], [0.04, 0.15], rtol=0.02)  # covers the mesh
    else:
        faces = model.mesh_facenum[model.geom_dataid[col]]
        assert {"full": faces == full_faces, "hull": faces <= full_faces,
                "decimate": faces <= 200}[mode], faces
    if mode == "hull":
        assert trimesh.load(str(out.parent / "meshes" / "link_hull.stl")).is_convex
    vis = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "arm_vis")
    assert model.mesh_facenum[model.geom_dataid[vis]] == full_faces  # the visual mesh is untouched


def test_hull_of_a_non_convex_link_is_smaller(tmp_path):
    tube = trimesh.creation.annulus(r_min=0.02, r_max=0.04, height=0.3, sections=64)
    model = build_scene(_skin_on(), _mesh_robot(tmp_path, tube), options=SceneOptions(collision="hull")).compile()
    col = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "arm_col")
    assert model.mesh_facenum[model.geom_dataid[col]] < len(tube.faces) / 1.5


def test_visual_meshes_dropped_on_request(tmp_path):
    robot = _mesh_robot(tmp_path, _capsule())
    model = build_scene(_skin_on(), robot, options=SceneOptions(visual=False, collision="hull")).compile()
    assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "arm_vis") == -1
    assert model.nmesh == 1  # only the hull is left


def test_broken_mesh_fails_naming_it_and_writes_nothing(tmp_path):
    robot_dir = tmp_path / "robot"
    robot_dir.mkdir()
    robot = _mesh_robot(robot_dir, _capsule())
    (robot_dir / "link.stl").write_bytes(b"solid x\n facet normal 0 0 nonsense\nendsolid\n")
    with pytest.raises(DesignError, match=r"link\.stl.*broken"):
        export_scene(_skin_on(), robot, tmp_path / "out", options=SceneOptions(collision="hull"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["robot"]


def test_non_manifold_mesh_fails_naming_it(tmp_path):
    box = trimesh.creation.box((0.2, 0.05, 0.05))
    a, b = box.edges_unique[0]
    fin = np.vstack([box.vertices, [[0.0, 0.0, 0.3]]])
    mesh = trimesh.Trimesh(fin, np.vstack([box.faces, [[a, b, len(box.vertices)]]]), process=False)
    robot_dir = tmp_path / "robot"
    robot_dir.mkdir()
    robot = _mesh_robot(robot_dir, trimesh.creation.box((0.2, 0.05, 0.05)))
    mesh.export(str(robot_dir / "link.stl"))
    with pytest.raises(DesignError, match=r"mesh 'link'.*link\.stl.*non-manifold"):
        export_scene(_skin_on(), robot, tmp_path / "out", options=SceneOptions(collision="decimate"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["robot"]


def test_prune_contacts_only_where_nothing_can_reach(tmp_path):
    robot = _mesh_robot(tmp_path, _capsule())
    design = _skin_on()
    pruned = build_scene(design, robot, options=SceneOptions(collision="hull")).compile()
    col = mujoco.mj_name2id(pruned, mujoco.mjtObj.mjOBJ_GEOM, "arm_col")
    assert pruned.geom_contype[col] == 0 and pruned.geom_conaffinity[col] == 0  # the box is 5 m away
    near = [Obstacle("post", "box", (0.05, 0.05, 0.5), pos=(0.3, 0, 0.5))]
    kept = build_scene(design, robot, near, SceneOptions(collision="hull")).compile()
    assert kept.geom_contype[col] == 1
    probe = [Obstacle("probe", "sphere", (0.01,), pos=(9, 9, 9), mocap=True)]
    assert build_scene(design, robot, probe, SceneOptions(collision="hull")).compile().geom_contype[col] == 1
    off = build_scene(design, robot, options=SceneOptions(collision="hull", prune_contacts=False)).compile()
    assert off.geom_contype[col] == 1


def test_cli_export(tmp_path, capsys):
    from skinsafe.core.app.cli import main

    design = make_sample_design("ur5", pitch=0.02)
    taxel_map.save(design, tmp_path / "map.json")
    assert main(["export", str(tmp_path / "map.json"), str(tmp_path / "scene"), "--probe", "0.01", "--touch"]) == 0
    model = mujoco.MjModel.from_xml_path(str(tmp_path / "scene" / "scene.xml"))
    assert model.nsensor == design.n_taxels and model.nmocap == 1
    assert main(["export", str(tmp_path / "missing.json"), str(tmp_path / "x")]) == 1
    assert "missing.json" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_export_into_an_unmakeable_folder_is_one_clear_error(tmp_path, capsys):
    from skinsafe.core.app.cli import main

    assert main(["sample", "--pitch", "0.03", "--out", str(tmp_path / "skin.json")]) == 0
    (tmp_path / "file").write_text("not a folder")
    assert main(["export", str(tmp_path / "skin.json"), str(tmp_path / "file" / "scene")]) == 2
    err = capsys.readouterr().err
    assert "skinsafe export: error:" in err and str(tmp_path / "file") in err and "Traceback" not in err
    assert not (tmp_path / "file" / "scene").exists()

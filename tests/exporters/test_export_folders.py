"""Exports into one folder never write over each other: MJCF, then URDF, then MJCF again, on a robot
description with Collada visuals and STL collision meshes (the UR5e); every body's meshes stay
where the design's robot has them (before, the URDF's re-centred meshes replaced the scene's
and its meshes sat 38-220 mm from their bodies; the second scene deleted the URDF's meshes)."""
import mujoco
import numpy as np
import pytest
from scipy.spatial import cKDTree

from skinsafe.core.app.cli import main
from skinsafe.core.robot.urdf_import import VISUAL_GROUP
from skinsafe.exporters.urdf import URDF_FILE, mesh_dir_of

MESH = mujoco.mjtGeom.mjGEOM_MESH
pytestmark = pytest.mark.xdist_group("public-robots")  # the session's UR5e skin (conftest.public_skin), made once


@pytest.fixture(scope="module")
def ur5e(public_skin):
    robot, _, path = public_skin("ur5e")
    return robot, path


def _mesh_points(model, visual_only: bool) -> dict[str, np.ndarray]:
    """Body name -> world points of its mesh geoms at the robot's joint values by name (home)."""
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    out: dict[str, list] = {}
    for g in range(model.ngeom):
        if model.geom_type[g] != MESH or (visual_only and model.geom_group[g] != VISUAL_GROUP):
            continue
        m = model.geom_dataid[g]
        v = model.mesh_vert[model.mesh_vertadr[m]:model.mesh_vertadr[m] + model.mesh_vertnum[m]]
        world = v @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g]
        out.setdefault(model.body(model.geom_bodyid[g]).name, []).append(world)
    return {b: np.concatenate(p) for b, p in out.items()}


def _worst_offset(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric largest nearest-neighbour distance between two point sets (m)."""
    return max(cKDTree(b).query(a)[0].max(), cKDTree(a).query(b)[0].max())


def _check_against_robot(model, robot, visual_only: bool) -> None:
    want, got = _mesh_points(robot.model, visual_only), _mesh_points(model, visual_only)
    assert set(want) <= set(got), set(want) - set(got)
    worst = {b: _worst_offset(want[b], got[b]) for b in want}
    assert max(worst.values()) < 1e-5, worst


def test_mjcf_then_urdf_then_mjcf_keeps_every_mesh_on_its_body(ur5e, tmp_path):
    robot, skin = ur5e
    out = tmp_path / "out"
    assert main(["export", str(skin), str(out)]) == 0
    assert main(["export", str(skin), str(out), "--urdf"]) == 0
    scene = mujoco.MjModel.from_xml_path(str(out / "scene.xml"))
    _check_against_robot(scene, robot, visual_only=True)
    assert main(["export", str(skin), str(out)]) == 0
    _check_against_robot(mujoco.MjModel.from_xml_path(str(out / "scene.xml")), robot, visual_only=True)
    _check_against_robot(mujoco.MjModel.from_xml_path(str(out / URDF_FILE)), robot, visual_only=False)  # kept
    assert sorted(p.name for p in out.iterdir()) == sorted(["scene.xml", "meshes", "taxel_map.json", URDF_FILE,
                                                            mesh_dir_of(URDF_FILE)])


def test_exported_home_keyframe_holds_the_arm(tmp_path):
    """The scene's `home` keyframe carries the servo targets: reset to it, the UR5 stays at home
    (a keyframe without ctrl drove every servo to 0 and the arm swung down at start)."""
    from skinsafe.core.design.sample import make_sample_design
    from skinsafe.core.robot.models import build_ur5
    from skinsafe.exporters.mjcf import export_scene

    robot = build_ur5()
    scene = export_scene(make_sample_design("ur5", robot=robot, pitch=0.03), robot, tmp_path / "out")
    model = mujoco.MjModel.from_xml_path(str(scene))
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, "home"))
    for _ in range(500):
        mujoco.mj_step(model, data)
    assert np.abs(data.qpos - robot.home).max() < 0.03

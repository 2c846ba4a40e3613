"""Built-in robots against their published kinematics; user URDF/MJCF files."""
import mujoco
import numpy as np
import pytest

from skinsafe.core.robot.models import PANDA_FLANGE_D, PANDA_MDH, UR5_DH, build_panda, build_ur5, load_robot
from skinsafe.core.skin.model import DesignError, RobotRef


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def _t(x, y, z):
    T = np.eye(4)
    T[:3, 3] = x, y, z
    return T


def _flange(robot, q):
    d = mujoco.MjData(robot.model)
    d.qpos[:] = q
    mujoco.mj_kinematics(robot.model, d)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = d.site("flange").xmat.reshape(3, 3), d.site("flange").xpos
    return T


def test_ur5_matches_standard_dh():
    robot = build_ur5()
    rng = np.random.default_rng(0)
    for q in rng.uniform(-np.pi, np.pi, (20, 6)):
        T = np.eye(4)
        for i in range(6):
            T = T @ _rz(q[i]) @ _t(0, 0, UR5_DH["d"][i]) @ _t(UR5_DH["a"][i], 0, 0) @ _rx(UR5_DH["alpha"][i])
        assert np.abs(_flange(robot, q) - T).max() < 1e-9
    # published zero-pose flange position of the UR5
    assert np.allclose(_flange(robot, np.zeros(6))[:3, 3], [-0.81725, -0.19145, -0.005491], atol=1e-6)


def test_panda_matches_modified_dh_and_limits():
    robot = build_panda()
    lo, hi = robot.model.jnt_range.T
    assert np.allclose(lo[3], -3.0718) and np.allclose(hi[5], 3.7525)
    rng = np.random.default_rng(1)
    for q in rng.uniform(lo, hi, (20, 7)):
        T = np.eye(4)
        for i in range(7):
            T = T @ _rx(PANDA_MDH["alpha"][i]) @ _t(PANDA_MDH["a"][i], 0, 0) @ _rz(q[i]) @ _t(0, 0, PANDA_MDH["d"][i])
        T = T @ _t(0, 0, PANDA_FLANGE_D)
        assert np.abs(_flange(robot, q) - T).max() < 1e-9


def test_home_poses_are_free_of_self_contact():
    for robot in (build_ur5(), build_panda()):
        d = mujoco.MjData(robot.model)
        d.qpos[:] = robot.home
        mujoco.mj_forward(robot.model, d)
        assert d.ncon == 0, robot.name


URDF = """<robot name="twolink">
  <link name="base"/>
  <link name="arm"><collision><geometry><cylinder radius="0.04" length="0.3"/></geometry></collision>
    <inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="cover"><collision><geometry><box size="0.05 0.05 0.05"/></geometry></collision>
    <inertial><mass value="0.1"/><inertia ixx="0.001" iyy="0.001" izz="0.001" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="arm"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="10" velocity="1.5"/></joint>
  <joint name="fix" type="fixed"><parent link="arm"/><child link="cover"/><origin xyz="0 0 0.2"/></joint>
</robot>"""


def test_urdf_keeps_fixed_links_and_velocity_limits(tmp_path):
    p = tmp_path / "two.urdf"
    p.write_text(URDF)
    robot = load_robot(RobotRef("urdf", "two", "two.urdf"), base_dir=tmp_path)
    assert "cover" in robot.body_names  # fusestatic off: the skin-carrying fixed link survives
    assert robot.vel_limits.tolist() == [1.5]


def test_mjcf_file_loads(tmp_path):
    p = tmp_path / "ur5.xml"
    p.write_text(build_ur5().spec.to_xml())
    robot = load_robot(RobotRef("mjcf", "", str(p)))
    assert robot.model.nv == 6 and "forearm_link" in robot.body_names


@pytest.mark.parametrize("ref,msg", [
    (RobotRef("builtin", "r2d2"), "builtin name 'r2d2' is unknown"),
    (RobotRef("urdf", "x", "missing.urdf"), "not found"),
    (RobotRef("sdf", "x", "a.sdf"), "use 'builtin', 'urdf' or 'mjcf'"),
])
def test_bad_robot_refs(ref, msg, tmp_path):
    with pytest.raises(DesignError, match=msg):
        load_robot(ref, base_dir=tmp_path)


def test_broken_mjcf_is_reported(tmp_path):
    p = tmp_path / "bad.xml"
    p.write_text("<mujoco><worldbody><body><geom type='sphere'/></body></worldbody>")
    with pytest.raises(DesignError, match="MuJoCo could not load"):
        load_robot(RobotRef("mjcf", "bad", str(p)))

"""Inertials of imported robots: the bundled Franka description gets its real masses by default (any
xacro file: the switch that adds them is found from the file),
and a URDF whose moving links have none says so, naming the links and the fix."""
import warnings
from pathlib import Path

import pytest

from skinsafe.core.robot.models import InertiaWarning, load_robot
from skinsafe.core.skin.model import RobotRef

ASSET = Path(__file__).resolve().parents[2] / "blend_assets" / "franka_description"
XACRO = str(ASSET / "robots" / "panda" / "panda.urdf.xacro")


def test_franka_sample_imports_with_its_real_inertials():
    with warnings.catch_warnings():
        warnings.simplefilter("error", InertiaWarning)
        robot = load_robot(RobotRef("urdf", "franka", XACRO, (str(ASSET),)))
    assert robot.model.body_mass.sum() == pytest.approx(16.69, abs=0.05)  # franka_description's inertials


def test_guessed_masses_are_named_with_the_fix(tmp_path):
    with pytest.warns(InertiaWarning, match=r"7 moving links have no <inertial> \(panda_link1, .*guessed 8\d\.\d kg"
                      r".*--xacro-arg NAME:=VALUE; this file declares .*gazebo"):
        robot = load_robot(RobotRef("urdf", "franka", XACRO, (str(ASSET),), {"gazebo": "false"}))
    assert robot.model.body_mass.sum() > 80
    urdf = tmp_path / "r.urdf"
    urdf.write_text('<robot name="r"><link name="a"/><link name="b"><collision><geometry><box size="0.1 0.1 0.1"/>'
                    '</geometry></collision></link><joint name="j" type="revolute"><parent link="a"/><child link="b"/>'
                    '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>')
    with pytest.warns(InertiaWarning, match=r"1 moving links have no <inertial> \(b\).*add <inertial> elements"):
        load_robot(RobotRef("urdf", "r", str(urdf)))


def test_the_switch_that_adds_inertials_is_found_from_the_file_not_its_package(tmp_path):
    """Any xacro file: of the switches it declares off, the one that gives every moving link its
    <inertial> without moving other links is turned on (here `sim`; `extra` adds a moving link)."""
    inertial = '<inertial><mass value="{m}"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial>'
    box = '<collision><geometry><box size="0.1 0.1 0.1"/></geometry></collision>'
    limit = '<limit lower="-1" upper="1" effort="1" velocity="1"/>'
    (tmp_path / "arm.urdf.xacro").write_text(
        f'<robot name="arm" xmlns:xacro="http://www.ros.org/wiki/xacro">'
        f'<xacro:arg name="extra" default="false"/><xacro:arg name="sim" default="false"/>'
        f'<link name="a"/><link name="b">{box}<xacro:if value="$(arg sim)">{inertial.format(m=2.5)}</xacro:if>'
        f'<xacro:if value="$(arg extra)">{inertial.format(m=9)}</xacro:if></link>'
        f'<joint name="j" type="revolute"><parent link="a"/><child link="b"/>{limit}</joint>'
        f'<xacro:if value="$(arg extra)"><link name="c">{box}{inertial.format(m=1)}</link>'
        f'<joint name="k" type="revolute"><parent link="b"/><child link="c"/>{limit}</joint></xacro:if></robot>')
    path = str(tmp_path / "arm.urdf.xacro")
    with warnings.catch_warnings():
        warnings.simplefilter("error", InertiaWarning)
        robot = load_robot(RobotRef("urdf", "arm", path))
    assert robot.model.body_mass.sum() == pytest.approx(2.5) and robot.model.nbody == 3
    with pytest.warns(InertiaWarning, match=r"1 moving links have no <inertial> \(b\)"):
        load_robot(RobotRef("urdf", "arm", path, (), {"sim": "false"}))

"""Inertials of imported robots: the bundled Franka description gets its real masses by default,
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

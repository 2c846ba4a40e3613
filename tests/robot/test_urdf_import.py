"""Robots from their ROS description: the bundled Franka xacro with package:// meshes (DAE visuals)."""
from pathlib import Path

import mujoco
import numpy as np
import pytest

from skinsafe.core.robot.models import load_robot
from skinsafe.core.skin.model import DesignError, RobotRef

ASSET = Path(__file__).resolve().parents[2] / "blend_assets" / "franka_description"
XACRO = ASSET / "robots" / "panda" / "panda.urdf.xacro"


@pytest.fixture(scope="module")
def franka():
    return load_robot(RobotRef("urdf", "franka", str(XACRO), (str(ASSET),)))


def test_xacro_with_package_paths_and_collada_visuals(franka):
    m = franka.model
    visual = [g for g in range(m.ngeom) if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH and m.geom_contype[g] == 0]
    assert len(visual) == 8  # link0..link7 DAE visuals, kept as non-colliding geoms
    assert min(m.mesh_facenum[m.geom_dataid[g]] for g in visual) > 10000  # the real CAD meshes
    assert m.nu == 7  # servos added: the description has no actuators
    lo, hi = m.jnt_range[:7].T
    assert ((franka.home[:7] >= lo) & (franka.home[:7] <= hi)).all()  # home inside the limits (joint 4 excludes 0)
    assert franka.home[3] == pytest.approx(0.5 * (lo[3] + hi[3]))
    assert franka.vel_limits[0] == pytest.approx(2.175)  # from the URDF's <limit velocity>


def test_no_self_contact_at_home(franka):
    d = mujoco.MjData(franka.model)
    d.qpos[:] = franka.home
    mujoco.mj_forward(franka.model, d)
    assert d.ncon == 0


def test_errors_name_link_and_file(tmp_path):
    with pytest.raises(DesignError, match=r"\$\(find franka_description\).*--package-dir") as e:
        load_robot(RobotRef("urdf", "f", str(XACRO)))
    said = str(e.value)  # once, one line, naming the file (xacro wraps our refusal and repeats it)
    assert said.startswith(f"robot file '{XACRO}': ") and said.count("$(find") == 1 and "\n" not in said
    bad = tmp_path / "bad.urdf.xacro"
    bad.write_text('<robot name="r" xmlns:xacro="http://www.ros.org/wiki/xacro"><link name="${nothere}"/></robot>')
    with pytest.raises(DesignError, match=r"xacro failed \(XacroException: name 'nothere' is not defined when") as e:
        load_robot(RobotRef("urdf", "r", str(bad)))
    assert "\n" not in str(e.value)
    urdf = tmp_path / "r.urdf"
    urdf.write_text('<robot name="r"><link name="base"><visual><geometry><mesh filename="package://pkg/m.dae"/>'
                    '</geometry></visual></link></robot>')
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "package.xml").write_text("<package><name>pkg</name></package>")
    with pytest.raises(DesignError, match="link 'base' visual #0: mesh file 'package://pkg/m.dae' not found"):
        load_robot(RobotRef("urdf", "r", str(urdf), (str(tmp_path),)))
    (tmp_path / "pkg" / "m.dae").write_text("<COLLADA>not really</COLLADA>")
    with pytest.raises(DesignError, match="link 'base' visual #0: mesh file .*m.dae' is broken"):
        load_robot(RobotRef("urdf", "r", str(urdf), (str(tmp_path),)))
    urdf.write_text('<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="planar">'
                    '<parent link="a"/><child link="b"/></joint></robot>')
    with pytest.raises(DesignError, match="joint 'j' has type 'planar'"):
        load_robot(RobotRef("urdf", "r", str(urdf)))


def test_surface_is_the_visual_mesh_within_budget(franka):
    from skinsafe.core.design.surface import body_surface

    s = body_surface(franka.model, "panda_link4", budget=4000)
    assert 3000 < len(s.triangles) <= 4000  # decimated to the budget, never subdivided
    full = body_surface(franka.model, "panda_link4", budget=10 ** 9)
    # the decimated surface stays on the described one (sub-millimetre)
    assert full.closest(s.vertices)[3].max() < 1e-3
    assert np.isfinite(s.corner_normals).all()

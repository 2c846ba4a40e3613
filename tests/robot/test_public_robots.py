"""Three public robot descriptions no one here wrote, end to end: the UR5e (xacro, Collada visuals,
STL collision), the Kinova Gen3 (xacro, Collada, hollow CAD housings) and the xArm7 (URDF, STL
links; `make robots`): import, design, export, collision at the real surface, poke."""
import json
import warnings

import mujoco
import numpy as np
import pytest

from skinsafe.core.app.cli import main
from skinsafe.core.bench.robot_import import bare_points
from skinsafe.core.design.surface import body_surface
from skinsafe.core.robot.catalog import description
from skinsafe.core.robot.models import load_robot
from skinsafe.core.sim.scene import build_scene
from skinsafe.core.sim.skin_collision import point_clearance, taxel_clearance
from skinsafe.core.skin.model import DesignError, RobotRef

# the xArm7's home is its zero pose, stretched straight up: a singular pose where no retraction
# within the joint speed limits gets far (10% of eq. 10's distance), so its slope is not checked
SINGULAR_HOME = {"xarm7"}
# one worker builds each robot's scene (its skin collision cut: 6-40 s) once for the module's tests; ungrouped,
# pytest-xdist hands the tests out one by one and both workers cut the same scene
pytestmark = pytest.mark.xdist_group("public-robots")


@pytest.fixture(scope="module", params=["gen3", "ur5e", "xarm7"])  # conftest.PUBLIC_LINKS
def robot_skin(request, public_skin):
    robot, design, path = public_skin(request.param)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no taxel farther than 1 mm from the contact surface
        scene = build_scene(design, robot)
    return robot, design, path, scene


def test_design_sits_on_the_visual_surface(robot_skin, public_skin):
    robot, design, _, _ = robot_skin
    assert sorted(design.bodies) == sorted(public_skin.links[robot.name]) and design.n_taxels >= 2 * 9
    for bi, b in enumerate(design.bodies):
        full = body_surface(robot.model, b, budget=10 ** 9)
        assert full.closest(design.taxels.positions[design.taxels.body == bi])[3].max() < 1e-4


def test_collision_where_the_surface_is_skinned_or_not(robot_skin):
    """Every link collides within 4 mm of its exposed surface, a skinned link's outside its taxel
    cells within 5 mm (the descriptions' own collision shapes stood 9-50 mm off it; skinned links
    kept them, shrunk under the skin), and every taxel is within 1 mm of the contact surface."""
    robot, design, _, scene = robot_skin
    bare = bare_points(robot.model, design, robot.home, n=200)
    skinned = bare_points(robot.model, design, robot.home, n=200, skinned=True)
    assert len(bare) >= 4 and not set(bare) & set(design.bodies) and set(skinned) == set(design.bodies)
    for points, limit in ((bare, 4e-3), (skinned, 5e-3)):
        gaps = point_clearance(scene, points, robot.home)
        worst = {b: float(np.abs(d).max()) for b, d in gaps.items()}
        assert max(worst.values()) < limit, worst
    assert np.abs(taxel_clearance(scene, design, robot.home)).max() <= 1e-3
    raw = point_clearance(robot.spec, {**bare, **skinned}, robot.home)
    assert min(float(np.abs(raw[b]).max()) for b in design.bodies) > 10e-3  # what the descriptions' shapes gave
    assert max(float(np.abs(d).max()) for d in raw.values()) > 10e-3


def test_export_and_home_keyframe(robot_skin, tmp_path):
    robot, design, path, _ = robot_skin
    out = tmp_path / "scene"
    assert main(["export", str(path), str(out), "--urdf"]) == 0
    model = mujoco.MjModel.from_xml_path(str(out / "scene.xml"))
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    np.testing.assert_allclose(data.qpos[:robot.model.nq], robot.home)
    for _ in range(250):
        mujoco.mj_step(model, data)
    assert np.abs(data.qpos[:robot.model.nq] - robot.home).max() < 0.05  # the servos hold home
    assert mujoco.MjModel.from_xml_path(str(out / "robot_skin.urdf")).nbody == robot.model.nbody + design.n_taxels


def test_poke_any_robot_has_its_multicontact_case(robot_skin, tmp_path):
    robot, design, path, _ = robot_skin
    out = tmp_path / "poke"
    assert main(["poke", "--map", str(path), "--out", str(out), "--depths", "0.0008,0.0016", "--epsilons", "1",
                 "--forms-stride", "1000"]) == 0
    res = json.loads((out / "poke_results.json").read_text())
    sweep = res["force_sweep"]
    assert sweep["body"] in design.bodies and len(sweep["force"]) == 2
    if robot.name not in SINGULAR_HOME:
        assert abs(sweep["slope"] - 0.01 / 12) < 0.1 * 0.01 / 12
    multi = res["multicontact"]
    assert multi and {tuple(r["bodies"]) for r in multi} == {tuple(multi[0]["bodies"])}
    assert sorted(multi[0]["bodies"]) == sorted(design.bodies) and multi[0]["into_contact_mm"] <= 0.5


def test_missing_xacro_arguments_are_named():
    ur5e, gen3 = description("ur5e"), description("gen3")
    with pytest.raises(DesignError, match=r"argument 'name' is not set.*--xacro-arg name:=VALUE"):
        load_robot(RobotRef("urdf", "ur", ur5e.path, ur5e.package_dirs))
    with pytest.raises(DesignError, match=r"'ur5x' in the missing path comes from xacro argument 'ur_type'"):
        load_robot(RobotRef("urdf", "ur", ur5e.path, ur5e.package_dirs, {"name": "ur"}))
    with pytest.raises(DesignError, match=r"'dof' in the missing path is built from an argument left empty "
                                          r"by default \(dof"):
        load_robot(RobotRef("urdf", "g", gen3.path, gen3.package_dirs))

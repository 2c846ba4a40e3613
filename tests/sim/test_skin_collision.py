"""The collision model fitted to the skin on a real robot description (Franka, CAD meshes)."""
import warnings
from pathlib import Path

import mujoco
import numpy as np

from skinsafe.core.app.design import design_robot
from skinsafe.core.bench.robot_import import pokes, self_contacts
from skinsafe.core.design.surface import cached_surfaces
from skinsafe.core.robot.models import load_robot
from skinsafe.core.sim.scene import Obstacle, SceneOptions, build_scene
from skinsafe.core.sim.skin_collision import taxel_clearance
from skinsafe.core.skin.model import RobotRef

ASSET = Path(__file__).resolve().parents[2] / "blend_assets" / "franka_description"


def test_skin_sits_on_the_contact_surface_and_feels_pokes():
    ref = RobotRef("urdf", "franka", str(ASSET / "robots/panda/panda.urdf.xacro"), (str(ASSET),))
    robot = load_robot(ref)
    bodies = ["panda_link2", "panda_link4"]
    design = design_robot(robot, ref, {"module": {"rows": 4, "cols": 4, "pitch": 0.012}, "bodies": bodies})[0]
    surfaces = cached_surfaces(robot.model, bodies)
    assert design.n_taxels >= 64
    # the robot's own collision shapes stand far above the skin: a warning says so
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        build_scene(design, robot, options=SceneOptions(collision="full"))
    assert any("from the contact surface" in str(w.message) for w in caught)
    raw = taxel_clearance(robot.spec, design, robot.home)
    assert np.abs(raw).max() > 5e-3
    spec = build_scene(design, robot, [Obstacle("poke", "sphere", (0.005,), pos=(0, 0, -5), mocap=True)])
    fitted = taxel_clearance(spec, design, robot.home)
    assert np.abs(fitted).max() <= 1e-3
    model = spec.compile()
    data = mujoco.MjData(model)
    data.qpos[:] = robot.home
    model.opt.gravity[:] = 0
    data.ctrl[:] = robot.home[model.jnt_qposadr[model.actuator_trnid[:, 0]]]
    mujoco.mj_forward(model, data)
    assert self_contacts(model, data) == 0
    assert pokes(model, data, design, surfaces, 60) >= 0.95

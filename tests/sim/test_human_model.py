"""The person of a scene: only the asked regions, the table's masses, a contact spring that gives
ISO/TS 15066's transient force `v sqrt(mu k)`, and a compliant attachment a push moves."""
import mujoco
import numpy as np
import pytest

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.sim.body_regions import REGIONS
from skinsafe.core.sim.human import Human, Part
from skinsafe.core.sim.scene import Obstacle, build_scene
from skinsafe.core.skin.model import DesignError

QUAT = (np.cos(np.pi / 4), 0, np.sin(np.pi / 4), 0)  # capsule axis along x


@pytest.fixture(scope="module")
def ur5():
    robot = build_ur5()
    return robot, make_sample_design("ur5", pitch=0.03, robot=robot)


def _impact(ur5, reg, m_ball, v, steps=40):
    robot, design = ur5
    human = Human([Part(reg, "capsule", (0.04, 0.12), pos=(1.0, 1.0, 0.5), quat=QUAT)], robot_mass=m_ball)
    ball = Obstacle("ball", "sphere", (0.04,), pos=(1.0, 0.9, 0.5), free=True, mass=m_ball)
    spec = build_scene(design, robot, [ball] + human.obstacles())
    human.attach(spec, ["ball"])
    spec.option.gravity = [0, 0, 0]
    model = spec.compile()
    human.bind(model)
    data = mujoco.MjData(model)
    data.qvel[model.jnt_dofadr[model.joint("ball_free").id] + 1] = v
    peak = 0.0
    for _ in range(steps):  # the first impact (the arm's attachment pulls it back later)
        mujoco.mj_step(model, data)
        peak = max(peak, float(human.forces(data)[0]))
    return model, data, human, peak


@pytest.mark.parametrize("reg, m_ball, v", [("lower_arm", 10.0, 1.0), ("hand", 5.0, 1.0), ("lower_arm", 3.0, 2.0),
                                            ("chest", 10.0, 0.5)])
def test_transient_force_follows_the_iso_spring(ur5, reg, m_ball, v):
    model, data, human, peak = _impact(ur5, reg, m_ball, v)
    r = REGIONS[reg]
    assert model.body_mass[human.body[0]] == r.mass_kg
    mu = 1 / (1 / r.mass_kg + 1 / m_ball)
    want = v * np.sqrt(mu * r.k_N_per_m)
    assert 0.85 * want < peak < 1.05 * want, (peak, want)  # light contact damping, 2 ms steps


def test_push_moves_the_person_and_the_attachment_pulls_back(ur5):
    model, data, human, _ = _impact(ur5, "lower_arm", 10.0, 1.0, steps=60)
    assert human.position(data, 0)[1] > 1.02  # pushed along +y by the ball
    human.move(0, (1.0, 1.2, 0.5))  # the person moves the arm: the springs take it there
    for _ in range(1500):
        mujoco.mj_step(model, data)
    assert np.allclose(human.position(data, 0), (1.0, 1.2, 0.5), atol=0.01)


def test_only_the_asked_regions_and_clear_errors(ur5):
    robot, design = ur5
    human = Human([Part("hand", "sphere", (0.04,), pos=(1, 1, 1))])
    spec = build_scene(design, robot, human.obstacles())
    human.attach(spec, ["forearm_link_0"])
    model = spec.compile()
    names = {model.body(i).name for i in range(model.nbody)}
    assert "human_hand" in names and not any(n.startswith("human_") and n != "human_hand" for n in names)
    assert model.npair == 1 and model.pair_solref[0, 0] < 0  # direct (stiffness, damping) form
    with pytest.raises(DesignError, match="each body region once"):
        Human([Part("hand", "sphere", (0.04,)), Part("hand", "sphere", (0.04,))])
    with pytest.raises(ValueError, match="unknown"):
        Human([Part("elbow", "sphere", (0.04,))])
    with pytest.raises(DesignError, match="robot_mass"):
        Human([Part("hand", "sphere", (0.04,))], robot_mass=-1)

"""Contact events of the collaboration experiment: kind from the contact's kinematics, the force and
pressure limits of ISO/TS 15066 for that kind, when the skin sensed it, which layers acted; and
the skin covering where the person is met."""
import mujoco
import numpy as np
import pytest

from skinsafe.core.experiments.collaboration_result import GAP_S, contact_events
from skinsafe.core.experiments.collaboration_scenario import CollabConfig
from skinsafe.core.experiments.collaboration_skin import _covered, cover
from skinsafe.core.sim.body_regions import REGIONS


def _trace(steps, parts, dt):
    z = np.zeros((steps, parts))
    return {"time_s": np.arange(steps) * dt, "force_N": z.copy(), "pressure_N_cm2": z.copy(),
            "sensed": z.astype(bool), "touched": z.astype(bool), "trapped": z.astype(bool), "pinched": z.astype(bool),
            "body": -np.ones((steps, parts), int)}


def test_kinds_limits_and_sensing():
    dt = 0.002
    tr = _trace(2000, 2, dt)
    # hand: a 50 ms impact (free: transient), sensed 4 ms after it began, 3 steps on bare surface
    tr["force_N"][100:125, 0] = np.r_[np.linspace(10, 300, 12), np.linspace(300, 10, 13)]
    tr["pressure_N_cm2"][100:125, 0] = tr["force_N"][100:125, 0]
    tr["touched"][103:125, 0] = True
    tr["sensed"][102:125, 0] = True
    tr["body"][100:125, 0] = 7
    # hand again: pressed against the table (trapped) at 150 N, 155 N/cm^2
    tr["force_N"][600:700, 0] = 150.0
    tr["pressure_N_cm2"][600:700, 0] = 155.0
    tr["trapped"][650, 0] = True
    tr["touched"][600:700, 0] = tr["sensed"][600:700, 0] = True
    # lower arm: 1 s held against the robot (free) at 200 N, a 40 ms gap inside: one event
    tr["force_N"][1000:1500, 1] = 200.0
    tr["force_N"][1200:1220, 1] = 0.0
    tr["touched"][1000:1500, 1] = True
    # lower arm: pinched between two links, 120 N
    tr["force_N"][1700:1750, 1] = 120.0
    tr["pinched"][1710, 1] = True
    tr["touched"][1700:1750, 1] = True
    acted = np.zeros((400, 3), bool)
    acted[21:30, 0] = True  # defensiveness during the first impact
    acted[121:140, 1] = True  # the cap during the clamp
    ev = contact_events(tr, ["hand", "lower_arm"], 0.01, acted, [f"link{i}" for i in range(10)])
    assert [(e["region"], e["kind"]) for e in ev] == [("hand", "transient"), ("hand", "clamp"),
                                                     ("lower_arm", "transient"), ("lower_arm", "quasi_static")]
    hit, clamp, held, pinch = ev
    hand, arm = REGIONS["hand"], REGIONS["lower_arm"]
    assert hit["limit_N"] == 2 * hand.quasi_static_N == 280 and hit["pressure_limit_N_cm2"] == 2 * 190
    assert np.isclose(hit["peak_N"], 300) and np.isclose(hit["ratio"], 300 / 280) and not hit["within"]
    assert hit["sensed"] and hit["sensed_ms"] == pytest.approx(4.0) and hit["bare_ms"] == pytest.approx(6.0)
    assert hit["robot_link"] == "link7" and hit["acted"] == "defensiveness"
    assert clamp["limit_N"] == 140 and clamp["pressure_limit_N_cm2"] == 190  # quasi-static, from the start
    assert np.isclose(clamp["ratio"], 150 / 140) and not clamp["within"] and clamp["acted"] == "pfl"
    assert held["duration_s"] == pytest.approx(1.0) and GAP_S > 0.04  # the gap did not split it
    assert held["peak_N"] == 200 and held["quasi_static_N"] == 200 and held["quasi_static_limit_N"] == arm.quasi_static_N
    assert np.isclose(held["ratio"], 200 / 160) and not held["sensed"] and held["sensed_ms"] is None
    assert pinch["limit_N"] == arm.quasi_static_N and pinch["within"] and held["acted"] == "none"
    for e in ev:
        assert e["within"] == (e["ratio"] <= 1.0)


@pytest.fixture(scope="module")
def ur5():
    from skinsafe.core.design.sample import make_sample_design
    from skinsafe.core.robot.models import build_ur5

    robot = build_ur5()
    return robot, make_sample_design("ur5", pitch=0.01, robot=robot)


def test_cover_puts_taxels_where_the_person_is_met_and_the_readout_senses_them(ur5):
    """Bare points the sample skin leaves (the flange's end face, the wrist 2 housing's rim): after
    `cover` a probe pressing there is sensed by `SkinReadout`, and the sample's taxels are kept."""
    from skinsafe.core.sim.readout import SkinReadout
    from skinsafe.core.sim.scene import Obstacle, build_scene

    robot, design = ur5
    points = [("wrist_3_link", np.array([0.0, 0.0, 0.072]), np.array([0.0, 0.0, 1.0])),
              ("wrist_3_link", np.array([0.03, 0.012, 0.072]), np.array([0.0, 0.0, 1.0])),
              ("wrist_2_link", np.array([-0.037, 0.0, 0.09]), np.array([-1.0, 0.0, 0.0]))]
    assert not any(_covered(design, b, p, n, 0.01) for b, p, n in points)
    new, bare = cover(design, robot, points, 0.01)
    assert not bare and all(_covered(new, b, p, n, 0.01) for b, p, n in points)
    assert new.n_taxels > design.n_taxels and {m.name for m in design.modules} <= {m.name for m in new.modules}
    m = robot.model
    d = mujoco.MjData(m)
    d.qpos[:] = robot.home
    mujoco.mj_kinematics(m, d)
    for body, p, n in points:
        bid = m.body(body).id
        R = d.xmat[bid].reshape(3, 3)
        probe = Obstacle("probe", "sphere", (0.01,), pos=tuple(d.xpos[bid] + R @ (p + n * 0.008)), mocap=True)
        model = build_scene(new, robot, [probe]).compile()
        data = mujoco.MjData(model)
        data.qpos[:len(robot.home)] = robot.home
        mujoco.mj_forward(model, data)
        readout = SkinReadout(model, new)
        assert readout.read(data).sum() > 0 and readout.last_missed == 0, body


def test_the_config_is_typed_and_the_committed_result_loads_with_it():
    """The committed result's `config` is the experiment's defaults; JSON round trip keeps every field; an unknown
    key is refused by name."""
    import json
    from pathlib import Path

    doc = json.loads((Path(__file__).resolve().parents[2] / "results/collaboration/collaboration.json").read_text())
    cfg = CollabConfig.from_json(doc["config"])
    assert cfg == CollabConfig() and cfg.to_json() == doc["config"] and list(doc["config"])[-1] == "seed"
    ours = CollabConfig(pfl_regions=("hand", "lower_arm"), samples=300, seed=4)
    assert CollabConfig.from_json(json.loads(json.dumps(ours.to_json()))) == ours
    assert ours.to_json()["pfl_regions"] == ["hand", "lower_arm"]
    with pytest.raises(ValueError, match=r"unknown keys \['pitch_m'\]"):
        CollabConfig.from_json({**doc["config"], "pitch_m": 0.01})
    with pytest.raises(AttributeError):
        cfg.seed = 1  # frozen

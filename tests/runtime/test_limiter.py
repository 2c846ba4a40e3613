"""The one command limiter (core/runtime/limiter.py) with the FR3's position-dependent velocity limits: pylibfranka
0.21.3 does not bind libfranka's computeUpper/LowerLimitsJointVelocity, so the reference here is their C++ text
(include/franka/rate_limiting.h) transcribed joint by joint, constants as printed there."""
import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.runtime.limiter import Limiter, limits_config
from skinsafe.core.sim.robot_driver import Contact, SimDriver
from skinsafe.hardware import franka

DT = franka.PERIOD_S


def libfranka_upper(q):
    t = 1e-3  # kJointVelocityLimitsTolerance
    return [min(2.62, max(0.0, -0.30 + math.sqrt(max(0.0, 12.0 * (2.75010 - q[0]))))) - t,
            min(2.62, max(0.0, -0.20 + math.sqrt(max(0.0, 5.17 * (1.79180 - q[1]))))) - t,
            min(2.62, max(0.0, -0.20 + math.sqrt(max(0.0, 7.00 * (2.90650 - q[2]))))) - t,
            min(2.62, max(0.0, -0.30 + math.sqrt(max(0.0, 8.00 * (-0.1458 - q[3]))))) - t,
            min(5.26, max(0.0, -0.35 + math.sqrt(max(0.0, 34.0 * (2.81010 - q[4]))))) - t,
            min(4.18, max(0.0, -0.35 + math.sqrt(max(0.0, 11.0 * (4.52050 - q[5]))))) - t,
            min(5.26, max(0.0, -0.35 + math.sqrt(max(0.0, 34.0 * (3.01960 - q[6]))))) - t]


def libfranka_lower(q):
    t = 1e-3
    return [max(-2.62, min(0.0, 0.30 - math.sqrt(max(0.0, 12.0 * (2.750100 + q[0]))))) + t,
            max(-2.62, min(0.0, 0.20 - math.sqrt(max(0.0, 5.17 * (1.791800 + q[1]))))) + t,
            max(-2.62, min(0.0, 0.20 - math.sqrt(max(0.0, 7.00 * (2.906500 + q[2]))))) + t,
            max(-2.62, min(0.0, 0.30 - math.sqrt(max(0.0, 8.00 * (3.048100 + q[3]))))) + t,
            max(-5.26, min(0.0, 0.35 - math.sqrt(max(0.0, 34.0 * (2.810100 + q[4]))))) + t,
            max(-4.18, min(0.0, 0.35 - math.sqrt(max(0.0, 11.0 * (-0.54092 + q[5]))))) + t,
            max(-5.26, min(0.0, 0.35 - math.sqrt(max(0.0, 34.0 * (3.019600 + q[6]))))) + t]


def fr3_limiter(**drop):
    """The limiter `skinsafe run --robot fr3` builds, through the record's JSON (what a replay rebuilds)."""
    limits = {"q_min": franka.Q_MIN, "q_max": franka.Q_MAX, "qd_max": franka.QD_MAX, "qdd_max": franka.QDD_MAX,
              "qddd_max": franka.QDDD_MAX, "qd_bounds": "fr3"}
    return Limiter(json.loads(json.dumps(limits_config({k: v for k, v in limits.items() if k not in drop}))))


frac = st.lists(st.floats(0, 1), min_size=7, max_size=7)
signed = st.lists(st.floats(-1, 1), min_size=7, max_size=7)


@settings(max_examples=300, deadline=None)
@given(frac, signed, st.lists(st.floats(-20, 20), min_size=7, max_size=7))
def test_the_fr3_limiter_keeps_libfranka_position_dependent_velocity_limits(q_frac, v_frac, cmd):
    """From any q in the FR3's range, moving at any speed inside its bounds there, any command for 300 ticks (q
    integrating what is sent, toward and into the joint limits): every command lies inside libfranka's bounds at
    the q it was sent from, and the position rule keeps q inside [q_min, q_max]."""
    q = franka.Q_MIN + np.array(q_frac) * (franka.Q_MAX - franka.Q_MIN)
    lo, hi = np.array(libfranka_lower(q)), np.array(libfranka_upper(q))
    lim = fr3_limiter()
    lim.last = np.where(np.array(v_frac) > 0, hi, -lo) * np.array(v_frac)  # moving, inside the bounds at q
    for _ in range(300):
        out = lim(np.array(cmd), q, DT)
        assert (out <= np.array(libfranka_upper(q)) + 1e-12).all() and (out >= np.array(libfranka_lower(q)) - 1e-12).all()
        q = q + out * DT
    assert (q <= franka.Q_MAX + 0.01).all() and (q >= franka.Q_MIN - 0.01).all()


@settings(max_examples=200, deadline=None)
@given(frac)
def test_the_bounds_equal_libfranka_at_random_q(q_frac):
    from skinsafe.core.runtime.limiter import fr3_velocity_bounds

    q = franka.Q_MIN + np.array(q_frac) * (franka.Q_MAX - franka.Q_MIN)
    lo, hi = fr3_velocity_bounds(q)
    np.testing.assert_allclose(hi, libfranka_upper(q), rtol=0, atol=1e-14)
    np.testing.assert_allclose(lo, libfranka_lower(q), rtol=0, atol=1e-14)


def test_near_a_joint_limit_the_bound_is_below_the_constant_limit():
    """Joint 1 held 0.05 rad below its limit (q = 2.6937): libfranka allows -0.3 + sqrt(12 x 0.0564) - 0.001 =
    0.5217 rad/s toward it; the constants with the stop rule would allow sqrt(2 x 10 x 0.05) = 1.0 rad/s. Away from
    it (joint 1 toward its far limit) the constant 2.62 holds."""
    q = np.array([franka.Q_MAX[0] - 0.05, 0, 0, -1.5, 0, 2.0, 0])
    with_bounds, constants = fr3_limiter(), fr3_limiter(qd_bounds=True)
    for _ in range(1000):
        a, b = with_bounds(np.full(7, 3.0), q, DT), constants(np.full(7, 3.0), q, DT)
    assert a[0] == pytest.approx(-0.3 + math.sqrt(12 * (2.7501 - q[0])) - 1e-3, abs=1e-9) == pytest.approx(0.5217, abs=1e-4)
    assert b[0] == pytest.approx(math.sqrt(20 * 0.05), abs=1e-9)
    assert a[1] == pytest.approx(min(2.62, -0.2 + math.sqrt(5.17 * 1.7918)) - 1e-3, abs=1e-9)  # 2.7437 capped: 2.619
    for _ in range(1000):
        a = with_bounds(np.full(7, -3.0), q, DT)
    assert a[0] == pytest.approx(-2.62 + 1e-3, abs=1e-9)


def test_inside_the_bounds_acceleration_and_jerk_hold():
    """Mid-range, a step command: every tick within the FR3's acceleration and jerk limits (libfranka's limitRate)."""
    lim = fr3_limiter()
    q, sent = np.array([0, 0, 0, -1.5, 0, 2.0, 0.0]), [np.zeros(7)]
    for i in range(400):
        sent.append(lim(np.full(7, 1.0 if i < 200 else -1.0), q, DT))
    acc = np.diff(sent, axis=0) / DT
    assert (np.abs(acc) <= franka.QDD_MAX + 1e-9).all() and (np.abs(np.diff(acc, axis=0)) / DT <= franka.QDDD_MAX + 1e-6).all()
    assert sent[200] == pytest.approx(np.ones(7), abs=1e-9)  # it reached the command


def test_the_record_names_the_bounds_and_a_replay_refuses_unknown_ones():
    config = limits_config(franka.FrankaDriver.limits(None))
    assert config["qd_bounds"] == "fr3" and Limiter(config).bounds is not None
    with pytest.raises(ValueError, match="qd_bounds 'ur5' is not one of \\['fr3'\\]"):
        Limiter({**config, "qd_bounds": "ur5"})


def test_the_sim_driver_has_no_position_dependent_bounds():
    """The sim's limits are unchanged: its constants and stop rule only (0.02 rad from a limit at 4 rad/s^2...)."""
    robot = build_ur5()
    drv = SimDriver(make_sample_design("ur5", robot=robot), robot, None, 0.002, Contact("poke", at=0.1), realtime=False)
    limits = drv.limits()
    assert "qd_bounds" not in limits and limits_config(limits)["qd_bounds"] is None
    lim = Limiter(limits_config(limits))
    assert lim.bounds is None
    q = robot.home.copy()
    out = [lim(np.full(6, 100.0), q, 0.002) for _ in range(2000)][-1]
    np.testing.assert_allclose(out, np.minimum(limits["qd_max"], np.sqrt(2 * limits["qdd_max"] * (limits["q_max"] - q))))

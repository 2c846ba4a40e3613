"""The FR3 driver against franky-sim (a MuJoCo server of the libfranka protocol) in its own process and
environment (`make franky-sim`), with the skin's readings from franky-sim's contacts through emulated
boards over pseudo-terminals: two processes, two protocols, no shortcut."""
import subprocess
import threading
import time
from pathlib import Path

import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from skinsafe.core.app.cli import main as skinsafe
from skinsafe.core.app.runtime_fr3 import APPROACH, contact_run
from skinsafe.core.sim.franky_world import WorldProcess, franky_python
from skinsafe.hardware import franka
from skinsafe.hardware.franka import FrankaDriver, rate_limit

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def fr3_map(tmp_path_factory):
    """A skin designed on franky-sim's own FR3 MJCF (mesh directory pointed at meshes/)."""
    subprocess.run(["make", "-s", "franky-sim"], cwd=ROOT, check=True)
    d = tmp_path_factory.mktemp("fr3")
    subprocess.run([str(franky_python()), "-m", "skinsafe.core.sim.franky_world", "mjcf", str(d / "fr3.xml")],
                   check=True, capture_output=True)
    assert skinsafe(["design", str(d / "fr3.xml"), "--bodies", "fr3_link5,fr3_link6", "--out",
                     str(d / "skin.json")]) == 0
    return d / "skin.json"


def test_fr3_limits_match_the_robot_model(fr3_map):
    model = mujoco.MjModel.from_xml_path(str(fr3_map.parent / "fr3.xml"))
    ranges = np.array([model.joint(n).range for n in franka.JOINT_NAMES])
    np.testing.assert_allclose(ranges[:, 0], franka.Q_MIN)
    np.testing.assert_allclose(ranges[:, 1], franka.Q_MAX)
    assert (franka.QD_MAX > 2.5).all() and (franka.QDD_MAX == 10).all()


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-50, 50), min_size=7, max_size=7), st.lists(st.floats(-1, 1), min_size=7, max_size=7),
       st.lists(st.floats(-1, 1), min_size=7, max_size=7))
def test_fr3_rate_limit_keeps_velocity_acceleration_and_jerk(cmd, v_frac, a_frac):
    """From any state inside the limits, any command (even far outside them) moves within them."""
    v0 = np.array(v_frac) * franka.QD_MAX * 0.99
    a0 = np.array(a_frac) * franka.QDD_MAX * 0.99
    v, a = v0, a0
    for _ in range(5):
        v1, a1 = rate_limit(np.array(cmd), v, a)
        assert (np.abs(v1) <= franka.QD_MAX + 1e-9).all()
        assert (np.abs(a1) <= franka.QDD_MAX + 1e-9).all()
        assert (np.abs(a1 - a) <= franka.QDDD_MAX * franka.PERIOD_S + 1e-9).all()
        np.testing.assert_allclose(v1, v + a1 * franka.PERIOD_S, atol=1e-12)
        v, a = v1, a1


def test_fr3_rate_limit_reaches_a_reachable_command():
    v, a = np.zeros(7), np.zeros(7)
    for _ in range(100):
        v, a = rate_limit(APPROACH, v, a)
    np.testing.assert_allclose(v, APPROACH, atol=0.011)


def test_fr3_contact_through_boards_retracts_the_arm(fr3_map, tmp_path):
    """Approach a sphere franky-sim holds in the arm's path; the boards' frames of its contact make the
    control retreat; the robot's measured velocity follows; the robot's clock was kept throughout."""
    run = contact_run(fr3_map, tmp_path, seconds=2.0)
    w, log = run["world"], run["log"]
    assert run["reason"] == "control ended the motion"
    assert w["onsets"], "the arm never touched the sphere"
    assert w["contacts_on_bare_surface"] == 0 and w["peak_N"] > 2.0
    assert w["communication_stops"] == 0 and w["longest_missed_run"] < franka_missed_limit()
    t, follows, sign, age = log[:, 0], log[:, 2], log[:, 3], log[:, 4]
    first_retreat = np.flatnonzero(sign < 0)[0]
    assert np.isfinite(age[first_retreat]), "the retreat was not started by a board frame holding the contact"
    assert t[first_retreat] >= w["onsets"][0]  # sensed after it happened, not before
    after = np.flatnonzero((t > t[first_retreat]) & (follows < 0))
    assert len(after), "the measured joint velocity never followed the retreat"
    assert run["frames"] > 0 and run["driver"]["ticks"] == len(log) + 1  # the last tick ended the motion
    gaps = np.diff(t) * 1e3  # the robot's 1 kHz states, in order (a slow tick lets whole ones pass)
    assert (gaps >= 1 - 1e-6).all() and np.allclose(gaps, np.round(gaps), atol=1e-6)


def franka_missed_limit():
    from skinsafe.core.sim.franky_world import MISSED_LIMIT
    return MISSED_LIMIT


@pytest.fixture
def fr3_robot(fr3_map, tmp_path):
    with WorldProcess(fr3_map, tmp_path / "world.json") as world:
        driver = FrankaDriver(world.host)
        yield world, driver
        driver.close()


def test_fr3_stops_are_named_and_ramp_to_zero(fr3_robot):
    world, driver = fr3_robot
    states = []

    def swing(s):
        states.append(s)
        return APPROACH

    threading.Timer(0.3, driver.stop, args=("operator pressed stop",)).start()
    assert driver.run(swing) == "operator pressed stop"
    assert driver.stats["ramp_ticks"] > 0
    last = []
    assert driver.run(lambda s: last.append(s)) == "control ended the motion"
    assert np.abs(last[0].qd).max() < 0.02  # the ramp brought the arm to rest
    assert abs(states[-1].qd[0]) > 0.1  # it had been moving

    def refuse(s):
        raise RuntimeError("command source silent for 0.2 s")
    assert driver.run(refuse) == "command source silent for 0.2 s"
    reason = driver.run(lambda s: np.full(7, np.nan))
    assert reason.startswith("fr3: control returned (7,)") and "7 finite values" in reason
    assert "7 finite values" in driver.run(lambda s: np.zeros(6))


def test_fr3_missed_cycles_trip_the_communication_constraint(fr3_robot):
    world, driver = fr3_robot
    n = []

    def slow_once(s):
        n.append(1)
        if len(n) == 100:
            time.sleep(0.05)  # 50 cycles without a command
        return np.zeros(7)

    reason = driver.run(slow_once)
    assert reason.startswith("fr3: the robot stopped the motion") and "communication_constraints_violation" in reason
    assert driver.run(lambda s: None) == "control ended the motion"  # the next motion starts again
    assert world.stop()["communication_stops"] == 1


def test_fr3_robot_gone_is_named(fr3_robot):
    world, driver = fr3_robot
    n = []

    def kill_at_50(s):
        n.append(1)
        if len(n) == 50:
            world.kill()
        return np.zeros(7)

    reason = driver.run(kill_at_50)
    assert reason.startswith("fr3: communication with the robot lost"), reason


def test_fr3_unreachable_host_is_one_line():
    with pytest.raises(franka.FrankaError, match=r"fr3: cannot connect to 127\.0\.0\.254: .*FCI"):
        FrankaDriver("127.0.0.254")



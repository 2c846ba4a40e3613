"""The loop in-process on the sim driver (no boards: readings straight from the sim's readout): the tap a
viewer reads while the robot moves, the exclusion policy (excluded taxels are 0 N to the layers, a NaN
anywhere else stops the robot), the robot-state watchdog, and `--seconds`."""
import threading
import time
from dataclasses import dataclass, field

import numpy as np
import pytest

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.runtime.commands import Hold
from skinsafe.core.runtime.layers import build_stack
from skinsafe.core.runtime.limiter import Limiter
from skinsafe.core.runtime.loop import Runtime, warm_up
from skinsafe.core.sim.robot_driver import Contact, SimDriver, SimFaults


@dataclass
class Readings:
    t: float
    force: np.ndarray
    seq: int
    board_age_s: dict = field(default_factory=dict)
    faults: list = field(default_factory=list)
    frames_lost: int = 0


class SimReadings:
    """A readings source on the sim's own readout (what the boards would stream, without them); `nan` taxels read NaN."""

    frame_period_s = 0.002

    def __init__(self, driver, nan=()):
        self.driver, self.nan, self.n_taxels, self.seq = driver, list(nan), driver.design.n_taxels, 0

    def newest(self):
        self.seq += 1
        f = self.driver.forces.copy()
        f[self.nan] = np.nan
        return Readings(0.0, f, self.seq, {0: 0.0})


@pytest.fixture(scope="module")
def ur5():
    robot = build_ur5()
    return robot, make_sample_design("ur5", robot=robot)


def _runtime(ur5, excluded=(), nan=(), faults=None, seconds=0.6):
    robot, design = ur5
    drv = SimDriver(design, robot, None, 0.002, Contact("poke", at=0.1), realtime=False, faults=faults)
    lim = drv.limits()
    stack = build_stack(design, robot.model, lim["qd_max"], lim["qdd_max"], drv.period_s)
    warm_up(stack, robot.home, design.taxels.thresholds["force"], drv.period_s)
    ex = np.zeros(design.n_taxels, bool)
    ex[list(excluded)] = True
    return drv, Runtime(drv, SimReadings(drv, nan), stack, Hold(6), ex, design.taxels.thresholds["force"],
                        seconds=seconds)


def test_the_tap_shows_every_tick_to_a_viewer_without_blocking(ur5):
    drv, rt = _runtime(ur5)
    seen, done = [], threading.Event()

    def viewer():  # polls as a viewer does, giving the loop's thread the interpreter between looks
        while not done.is_set():
            f = rt.tap.latest()
            if f is not None and (not seen or f is not seen[-1]):
                seen.append(f)
            time.sleep(0.001)

    th = threading.Thread(target=viewer)
    th.start()
    out = rt.run(settle_s=0.0)
    done.set()
    th.join()
    assert out.kind == "end" and "0.6 s" in out.reason
    t = [f.t for f in seen]
    assert len(seen) > 10 and all(np.diff(t) >= 0)
    assert any(f.retracting for f in seen) and max(np.abs(f.command).max() for f in seen) > 0.05  # the poke's retraction
    last = rt.tap.latest()
    assert last.stop == out.reason and not last.command.any()  # the stop is the last frame: zero velocity


def test_excluded_taxels_read_zero_and_a_nan_anywhere_else_stops_the_robot(ur5):
    drv, rt = _runtime(ur5, excluded=[5, 6], nan=[5, 6])
    assert rt.run(settle_s=0.0).kind == "end"  # NaN only where excluded: the layers never see it
    drv, rt = _runtime(ur5, excluded=[5], nan=[5, 7])
    out = rt.run(settle_s=0.0)
    assert out.kind == "fault" and out.watchdog == "reading-nonfinite" and "first taxel 7" in out.reason and out.ticks == 0


def test_a_robot_state_that_stops_updating_stops_the_robot(ur5):
    drv, rt = _runtime(ur5, faults=SimFaults(freeze_at=0.2))
    out = rt.run(settle_s=0.0)
    assert out.watchdog == "robot-frozen" and "state not updating" in out.reason
    assert drv.stats.stop_t == pytest.approx(0.2, abs=0.01)  # within a few periods of the freeze


def test_run_tdm_puts_the_strategy_filter_and_the_modulation_on_the_plan(ur5, tmp_path):
    """`skinsafe run --tdm FILE` (build_stack with a learned danger model): a plan is filtered by the TDM's strategy
    filter and then modulated by its danger potential, exactly as the two layers do on their own (it once crashed on
    the first warm-up tick: the modulation was handed an already wrapped potential)."""
    import torch

    from skinsafe.core.safety.modulation import ModulationLayer
    from skinsafe.core.safety.potential import DangerPotential
    from skinsafe.core.safety.stack import StrategyFilter
    from skinsafe.core.safety.tdm import TactileDangerModel, load_tdm, save_tdm

    robot, design = ur5
    torch.manual_seed(3)
    save_tdm(TactileDangerModel(6, 6, design.n_taxels, hidden=(16, 16)), tmp_path / "tdm.pt")
    qd_max, qdd_max = np.full(6, 3.0), np.full(6, 10.0)
    stack = build_stack(design, robot.model, qd_max, qdd_max, 0.002, tdm_path=str(tmp_path / "tdm.pt"))
    warm_up(stack, robot.home, design.taxels.thresholds["force"], 0.002)
    plan = np.array([0.01, -0.01, 0.005, 0.0, 0.01, -0.005])  # within one tick's acceleration from rest
    v = stack.tick(0.0, robot.home, {"force": np.zeros(design.n_taxels)}, plan, 0.002)
    tdm = load_tdm(tmp_path / "tdm.pt")
    want, f = ModulationLayer(DangerPotential(tdm))(robot.home, StrategyFilter(tdm)(robot.home, plan))
    assert 0.0 < f < 1.0 and np.isclose(stack.last_f, f, rtol=1e-5)
    np.testing.assert_allclose(v, want, rtol=1e-5, atol=1e-9)
    assert not stack.flags, stack.flags

    wrong = TactileDangerModel(6, 6, design.n_taxels + 1, hidden=(16, 16))
    save_tdm(wrong, tmp_path / "other.pt")
    with pytest.raises(ValueError, match=f"predicts {design.n_taxels + 1} taxels, the map has {design.n_taxels}"):
        build_stack(design, robot.model, qd_max, qdd_max, 0.002, tdm_path=str(tmp_path / "other.pt"))


WARM_CHECK = """
import json, sys
import numpy as np, torch
from skinsafe.core.app.precompile import cached_kernels
from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.runtime.layers import build_stack
from skinsafe.core.runtime.loop import warm_up
from skinsafe.core.safety.tdm import TactileDangerModel, save_tdm

robot = build_ur5()
design = make_sample_design("ur5", robot=robot)
n, th = design.n_taxels, design.taxels.thresholds["force"]
torch.manual_seed(3)
save_tdm(TactileDangerModel(6, 6, n, hidden=(16, 16)), sys.argv[1])
loaded = lambda: {f"{k.__name__}{s}" for ks in cached_kernels().values() for k in ks for s in k.signatures}
new = set()
for tdm in (None, sys.argv[1]):  # the retraction alone first: the TDM's warm-up loads more
    stack = build_stack(design, robot.model, np.full(6, 3.0), np.full(6, 10.0), 0.002, tdm_path=tdm)
    warm_up(stack, robot.home, th, 0.002)
    before = loaded()
    stack.tick(0.0, robot.home.copy(), {"force": np.zeros(n)}, np.full(6, 0.01), 0.002)
    rng = np.random.default_rng(5)
    for case in range(12):  # contact onsets while the arm moves at up to its fastest, one taxel or a patch
        stack.reset()
        moving = rng.uniform(-1, 1, 6) * stack.vel_limits
        stack.last = moving.copy()
        force = np.zeros(n)
        force[rng.choice(n, 1 if case % 2 else 40, replace=False)] = rng.uniform(1, 20) * th.max()
        for k in range(6):
            stack.tick(0.002 * k, robot.home.copy(), {"force": force}, moving, 0.002, qdot=moving)
    new |= loaded() - before
print(json.dumps(sorted(new)))
"""


def test_after_the_warm_up_the_robots_first_tick_and_first_contact_load_no_kernel(tmp_path):
    """`warm_up` runs every kernel the first ticks call, the plan's too (strategy filter, modulation of a plan), and
    those of a contact met while the arm moves (the retraction's first level bound by the acceleration box: it once
    loaded `qp._first_level` on the FR3's first contact, a 6-19 ms tick at 16k taxels): a
    kernel's first call loads it from numba's cache (tens of ms) or compiles it (seconds) on the loop's core, which
    once starved the boards' reader on the first tick of `skinsafe run --tdm` (a watchdog stop, 1 run in 4). A fresh
    process: no earlier test may have loaded them."""
    import json
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", WARM_CHECK, str(tmp_path / "tdm.pt")], capture_output=True, text=True,
                         check=True, timeout=300).stdout
    assert json.loads(out.strip().splitlines()[-1]) == []


class Sweep:
    """The command source: the shoulder pan at `v` rad/s, the other joints held."""

    spec, stale_s, refused, intrusion = "sweep", None, 0, None

    def __init__(self, v):
        self.v = np.array([v, 0, 0, 0, 0, 0], float)

    def start(self, q0):
        pass

    def __call__(self, t, q):
        return self.v

    def age(self):
        return 0.0


class Ticks(list):
    put = list.append


def test_the_sim_arm_reaches_its_commanded_speed_in_the_time_its_acceleration_limit_takes(ur5):
    """The limits start from the last command sent, not from the measured velocity: started from the measured one, the
    sim's servo (about 60 ms behind the command) let the arm gain about 0.5 rad/s^2 of its 15, and 1.57 rad/s took
    seconds. The command reaches it in v / acc (+1 period), the arm 95% of it in that + 3 x the servo's lag (0.2 s)."""
    robot, design = ur5
    drv = SimDriver(design, robot, None, 0.002, realtime=False)
    lim = drv.limits()
    stack = build_stack(design, robot.model, lim["qd_max"], lim["qdd_max"], drv.period_s)
    warm_up(stack, robot.home, design.taxels.thresholds["force"], drv.period_s)
    v, ticks = 0.5 * lim["qd_max"][0], Ticks()
    rt = Runtime(drv, SimReadings(drv), stack, Sweep(v), np.zeros(design.n_taxels, bool),
                 design.taxels.thresholds["force"], recorder=ticks, seconds=0.4, limiter=Limiter(lim, drv.period_s))
    assert rt.run(settle_s=0.0).kind == "end"
    ticks = [k for k in ticks if "stop" not in k.flags]  # the sim's stop is a zero (not a ramp): not this test's
    t = np.array([k.t for k in ticks]) - ticks[0].t
    sent, measured = np.array([k.command[0] for k in ticks]), np.array([k.qd[0] for k in ticks])
    ramp_s = v / lim["qdd_max"][0]
    assert t[np.argmax(sent >= v * 0.999)] <= ramp_s + drv.period_s and sent.max() <= v + 1e-9
    assert np.abs(np.diff(sent)).max() <= lim["qdd_max"][0] * drv.period_s * (1 + 1e-9)  # never over the limit
    assert measured.max() >= 0.95 * v and t[np.argmax(measured >= 0.95 * v)] <= ramp_s + 0.2

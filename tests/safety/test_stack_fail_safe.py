"""The safety stack and the defensiveness layer fail safe: bad numbers, clocks, thresholds."""
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.safety.defensiveness import DefensivenessLayer
from skinsafe.core.safety.limits import brake
from skinsafe.core.safety.modulation import ModulationLayer
from skinsafe.core.safety.potential import DangerPotential
from skinsafe.core.safety.stack import SafetyStack, StrategyFilter
from skinsafe.core.safety.tdm import TactileDangerModel

ROBOT = build_ur5()
DESIGN = make_sample_design("ur5", robot=ROBOT)
KIN = TaxelKinematics(ROBOT.model, DESIGN)
N, DT = DESIGN.n_taxels, 0.002
PLAN = np.array([0.8, -0.6, 0.5, 0.3, -0.2, 0.4])


def layer(**kw):
    return DefensivenessLayer(KIN, DESIGN.taxels.thresholds, ROBOT.vel_limits, ROBOT.acc_limits, dt=DT, **kw)


def tdm():
    torch.manual_seed(0)
    return TactileDangerModel(6, 6, 32, (16, 16)).eval()


def ramp(stack, ticks=60, q=None):
    """Run the plan until it is at speed; returns the last command."""
    for k in range(ticks):
        out = stack.tick(k * DT, ROBOT.home if q is None else q, {"force": np.zeros(N)}, PLAN, DT)
    return out


@pytest.mark.parametrize("where", ["tdm", "potential"])
@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_bad_tdm_or_potential_sends_the_brake_never_the_plan(where, value):
    model = tdm()
    strategy = StrategyFilter(model)
    mod = ModulationLayer(DangerPotential(model))
    stack = SafetyStack(ROBOT.vel_limits, layer(), mod if where == "potential" else None, strategy, dt=DT)
    prev = ramp(stack)
    assert np.abs(prev).max() > 0.1
    if where == "tdm":
        strategy.fast.log_safety = lambda s, a: np.full(len(a), value)
    else:
        mod._eval = lambda s, a: (np.full(1, value), np.zeros((1, 6)))
    out = stack.tick(0.2, ROBOT.home, {"force": np.zeros(N)}, PLAN, DT)
    assert np.array_equal(out, brake(prev, stack.limits)) and stack.info.safe
    assert stack.flags["nonfinite"] == 1 and stack.flags[f"nonfinite:{where}"] == 1


def test_strategy_only_stack_with_nan_tdm_stops():
    strategy = StrategyFilter(tdm())
    strategy.fast.log_safety = lambda s, a: np.full(len(a), np.nan)
    stack = SafetyStack(ROBOT.vel_limits, strategy=strategy, dt=DT)  # no acceleration limit: the brake is a stop
    assert np.array_equal(stack.tick(0.0, ROBOT.home, None, PLAN, DT), np.zeros(6))


def test_modulated_command_is_acceleration_limited():
    """Modulation after the layers can change the command abruptly: the final limits catch it."""
    model = tdm()
    stack = SafetyStack(ROBOT.vel_limits, layer(), ModulationLayer(DangerPotential(model)), dt=DT)
    prev = np.zeros(6)
    rng = np.random.default_rng(0)
    for k in range(200):
        out = stack.tick(k * DT, ROBOT.home, {"force": np.zeros(N)}, rng.uniform(-3, 3, 6), DT)
        vel, acc = stack.limits.violations(out, prev)
        assert not vel and not acc
        prev = out


@pytest.mark.parametrize("t_bad", [np.nan, np.inf, -np.inf])
def test_bad_clock_never_latches(t_bad):
    L = layer()
    f = np.zeros(N)
    i = int(np.flatnonzero(DESIGN.taxels.body == 1)[40])
    f[i] = 20.0
    out = L.tick(t_bad, ROBOT.home, {"force": f}, PLAN)  # a touch on a bad tick: safe, nothing stored
    assert L.info.safe and np.array_equal(out, np.zeros(6)) and not L.active
    L.tick(0.0, ROBOT.home, {"force": f}, PLAN)  # the next finite tick sees it
    assert list(L.pool) == [i]
    outs = [L.tick(k * DT, ROBOT.home, {"force": 0 * f}) for k in range(1, 300)]
    assert not L.active and np.array_equal(outs[-1], np.zeros(6))  # retracted, then stopped: no freeze


def test_clock_going_backwards_resets_and_bad_q_does_not_hold_the_last_velocity():
    L = layer()
    for k in range(50):
        out = L.tick(k * DT, ROBOT.home, {"force": np.zeros(N)}, PLAN)
    f = np.zeros(N)
    f[int(np.flatnonzero(DESIGN.taxels.body == 2)[10])] = 20.0
    L.tick(0.1, ROBOT.home, {"force": f}, PLAN)
    assert L.active
    L.tick(0.05, ROBOT.home, {"force": 0 * f}, PLAN)  # backwards
    assert not L.active and L.flags["clock_reset"] == 1
    q = ROBOT.home.copy()
    q[2] = np.nan
    prev = L.last.copy()
    out = L.tick(0.052, q, {"force": 0 * f}, PLAN)
    assert np.array_equal(out, brake(prev, L.limits))
    out = L.tick(0.054, ROBOT.home, {"force": 0 * f}, PLAN)  # q finite again: the plan, from the braked command
    assert L.info.nonfinite == () and np.abs(out - brake(prev, L.limits)).max() <= 15.0 * DT + 1e-12


def test_severity_counts_only_stimuli_over_their_thresholds():
    """90 C under a 100 C threshold must not enlarge a force retraction."""
    th = dict(DESIGN.taxels.thresholds, temperature=np.full(N, 100.0))
    i = int(np.flatnonzero(DESIGN.taxels.body == 1)[40])
    f, temp = np.zeros(N), np.full(N, 25.0)
    f[i], temp[i] = 2.5, 90.0  # 0.002 m/C * 90 C would outrank 0.05 m/N * 2.5 N
    L = DefensivenessLayer(KIN, th, ROBOT.vel_limits, ROBOT.acc_limits, dt=DT)
    L.tick(0.0, ROBOT.home, {"force": f, "temperature": temp})
    assert L.desired_distance()[0] == pytest.approx(0.05 * 2.5 / 12)
    temp[i] = 130.0  # over its threshold: it counts, with its own gain
    L.reset()
    L.tick(0.0, ROBOT.home, {"force": f, "temperature": temp})
    assert L.desired_distance()[0] == pytest.approx(0.002 * 130.0 / 12)


# ---- the measured joint velocity (distinct from the planned command)

def test_limits_start_from_the_last_command_not_the_measured_velocity():
    """The robot lags: it measures 0 while the last command was at speed. The next command differs from the last
    command by at most acc * dt (as ros2_control's and libfranka's rate limits): started from the measured
    velocity, a servo lagging by tau would let the arm gain only acc * dt / tau."""
    stack = SafetyStack(ROBOT.vel_limits, layer(), dt=DT)
    last = ramp(stack)
    step = stack.limits.acc * DT
    assert np.abs(last).max() > 4 * step.max()
    measured = np.zeros(6)
    out = stack.tick(0.2, ROBOT.home, {"force": np.zeros(N)}, PLAN, DT, qdot=measured)
    assert np.all(np.abs(out - last) <= step * (1 + 1e-9))
    assert np.abs(out - measured).max() > 2 * step.max()  # it did not start from the measured velocity


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_nonfinite_measured_velocity_brakes_and_is_counted(value):
    stack = SafetyStack(ROBOT.vel_limits, layer(), dt=DT)
    last = ramp(stack)
    bad = last.copy()
    bad[2] = value
    out = stack.tick(0.2, ROBOT.home, {"force": np.zeros(N)}, PLAN, DT, qdot=bad)
    assert np.array_equal(out, brake(last, stack.limits)) and stack.info.safe
    assert stack.flags["nonfinite:qdot"] == 1 and stack.flags["nonfinite"] == 1
    nxt = stack.tick(0.202, ROBOT.home, {"force": np.zeros(N)}, PLAN, DT, qdot=out)  # nothing latches
    assert not stack.info.safe and np.abs(nxt).max() > np.abs(out).max()
    with pytest.raises(ValueError, match="measured joint velocities"):
        stack.tick(0.204, ROBOT.home, {"force": np.zeros(N)}, PLAN, DT, qdot=np.zeros(5))


def test_measured_motion_into_a_contact_is_flagged():
    """While a taxel retracts, a measured velocity that carries it into its contact raises
    `pushing` (counted); one that carries it out does not."""
    stack = SafetyStack(ROBOT.vel_limits, layer(), dt=DT)
    force = np.zeros(N)
    taxel = int(np.argmax(KIN.body_id))
    force[taxel] = 40.0
    stack.tick(0.0, ROBOT.home, {"force": force}, np.zeros(6), DT)
    a = stack.defensiveness.A[0]  # a . qdot: the taxel's speed along its retraction axis
    into = -0.05 * a / np.linalg.norm(a)
    stack.tick(0.002, ROBOT.home, {"force": np.zeros(N)}, np.zeros(6), DT, qdot=into)
    assert stack.info.pushing and stack.flags["pushing"] == 1
    stack.tick(0.004, ROBOT.home, {"force": np.zeros(N)}, np.zeros(6), DT, qdot=-into)
    assert not stack.info.pushing and stack.flags["pushing"] == 1



# ---- missing readings: a silent board is a fault, never "no contact"

def _silent(kind, force, rng):
    """Readings with a board gone quiet: none, an empty dict, another stimulus only, the force
    array without one board's block, or that block NaN (the stream's value before a first frame)."""
    if kind == "none":
        return None
    if kind == "empty":
        return {}
    if kind == "other":
        return {"temperature": np.full(N, 25.0)}
    board = np.flatnonzero(DESIGN.taxels.board == rng.choice(np.unique(DESIGN.taxels.board)))
    return {"force": np.delete(force, board)} if kind == "short" else {"force": np.where(np.isin(np.arange(N), board),
                                                                                            np.nan, force)}


def _stack(config):
    model = tdm()
    mod = ModulationLayer(DangerPotential(model)) if "modulation" in config else None
    strategy = StrategyFilter(model) if "strategy" in config else None
    return SafetyStack(ROBOT.vel_limits, layer(), mod, strategy, dt=DT) if config != "layer" else layer()


@settings(max_examples=40, deadline=None)
@given(config=st.sampled_from(["layer", "retraction", "retraction+modulation", "retraction+strategy+modulation"]),
       kind=st.sampled_from(["none", "empty", "other", "short", "board_nan"]), touched=st.booleans(),
       at=st.integers(1, 30), seed=st.integers(0, 1000))
def test_missing_readings_brake_and_are_counted_in_every_configuration(config, kind, touched, at, seed):
    """At speed on a plan (and, with `touched`, retracting from a touch at tick 0), one tick's
    readings lose a board: that tick sends the brake, or the ongoing retraction that keeps every
    contacted taxel out of its contact, never the plan; the fault is counted; the next tick with
    readings goes on (nothing latches)."""
    rng = np.random.default_rng(seed)
    unit = _stack(config)
    d = unit if config == "layer" else unit.defensiveness
    force = np.zeros(N)
    if touched:
        force[rng.choice(N, 2, replace=False)] = 30.0
    prev = np.zeros(6)
    for k in range(at + 2):
        r = _silent(kind, force, rng) if k == at else {"force": force if k == 0 else np.zeros(N)}
        out = unit.tick(k * DT, ROBOT.home, r, PLAN, DT)
        assert np.all(np.abs(out - prev) <= ROBOT.acc_limits * DT * (1 + 1e-9))
        if k == at:
            flag = "nonfinite:readings:force" if kind == "board_nan" else "missing:force"
            assert unit.flags[flag] == 1 and unit.info.safe == (not d.active)
            if d.active:  # the retraction goes on: no contacted taxel is moved in, and it is not the plan
                assert np.all(d.A @ out >= -1e-6) and not np.allclose(out, PLAN)
            else:
                assert np.array_equal(out, brake(prev, d.limits))
        prev = out
    assert unit.flags["missing"] + unit.flags["nonfinite"] == 1  # the next tick with readings: no fault


# ---- dt: never assumed

def test_dt_is_required_and_must_match_the_layer():
    with pytest.raises(ValueError, match="give dt, the control period"):
        SafetyStack(ROBOT.vel_limits, layer())
    with pytest.raises(ValueError, match="dt is 0.01 s but the defensiveness layer was built for 0.002 s"):
        SafetyStack(ROBOT.vel_limits, layer(), dt=0.01)


def test_the_ticks_dt_sets_the_acceleration_step():
    """A stack built for 10 ms and ticked every 10 ms may change each joint by acc * 10 ms per
    tick (the collaboration scene's stack assumed 2 ms: a fifth of the robot's acceleration)."""
    d = DefensivenessLayer(KIN, DESIGN.taxels.thresholds, ROBOT.vel_limits, ROBOT.acc_limits, dt=0.01)
    stack = SafetyStack(ROBOT.vel_limits, d, dt=0.01)
    out = stack.tick(0.0, ROBOT.home, {"force": np.zeros(N)}, np.full(6, 3.0), 0.01)
    assert np.allclose(out, 15.0 * 0.01)
    out = stack.tick(0.004, ROBOT.home, {"force": np.zeros(N)}, np.full(6, 3.0), 0.004)  # a measured short tick
    assert np.allclose(out, 15.0 * 0.014)
    out = stack.tick(0.005, ROBOT.home, {"force": np.zeros(N)}, np.full(6, 3.0), 0.0)  # dt = 0: a bad input
    assert np.allclose(out, 15.0 * (0.014 - 0.01)) and stack.flags["nonfinite:dt"] == 1  # braked by the nominal period


# ---- a retraction stops short of the obstacles the potential knows (ModulationLayer.stop)

class Ramp(torch.nn.Module):
    """f = sigmoid(g . s + c): danger rises along g (an obstacle the potential knows on that side)."""

    def __init__(self, g, c):
        super().__init__()
        self.g, self.c = torch.tensor(g, dtype=torch.float32), float(c)

    def forward(self, s, a):
        return torch.sigmoid(s @ self.g + self.c)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), stop=st.sampled_from([0.3, 0.6, 0.9]), f=st.floats(0.0, 1.0))
def test_stop_short_keeps_the_brake_within_the_stop_level(seed, stop, f):
    """The retraction v is scaled (direction kept, never sped up) so that the potential's rise along
    the brake from it, S n.v, stays within stop - f; it passes untouched where it already does."""
    from skinsafe.core.safety.viability import braking_horizon

    rng = np.random.default_rng(seed)
    stack = SafetyStack(ROBOT.vel_limits, layer(), ModulationLayer(Ramp(np.ones(6), 0.0), stop=stop), dt=DT)
    stack.modulation.normal = rng.normal(size=(1, 6)) * 10 ** rng.uniform(-2, 2)
    v, prev = rng.uniform(-3, 3, 6), rng.uniform(-3, 3, 6)
    out = stack._stop_short(v, prev, f, DT)
    rise = lambda x: float(stack.modulation.normal[0] @ x)  # noqa: E731
    S, room = braking_horizon(prev, stack.limits.acc, DT), max(stop - f, 0.0)
    lam = out @ v / (v @ v)
    assert np.allclose(out, lam * v) and 0 <= lam <= 1
    assert rise(out) * S <= room + 1e-12
    assert lam == 1 or rise(v) * S > room


def test_a_retraction_into_the_known_danger_is_slowed():
    """A steep potential that rises along the retraction, 0.01 below the stop level 0.3: the stack with
    the stop level retracts slower than the same stack without it (None)."""
    touch = np.zeros(N)
    touch[np.random.default_rng(0).choice(N, 2, replace=False)] = 40.0
    probe = layer()
    probe.tick(0.0, ROBOT.home, {"force": touch})
    g = probe.tick(0.1, ROBOT.home, {"force": np.zeros(N)})  # the retraction's direction: danger rises along it
    g *= 100 / np.linalg.norm(g)
    c = np.log(0.29 / 0.71) - g @ ROBOT.home  # f(home) = 0.29
    speed = {}
    for level in (0.3, None):
        stack = SafetyStack(ROBOT.vel_limits, layer(), ModulationLayer(Ramp(g, c), tangent_gain=0.0, stop=level), dt=DT)
        for k in range(100):
            out = stack.tick(k * DT, ROBOT.home, {"force": touch if k == 0 else np.zeros(N)}, PLAN, DT)
        speed[level] = np.linalg.norm(out)
    assert speed[0.3] < 0.8 * speed[None]


def test_stop_level_is_validated():
    with pytest.raises(ValueError, match="'stop' is 1.5"):
        ModulationLayer(Ramp(np.ones(6), 0.0), stop=1.5)

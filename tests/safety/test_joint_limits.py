"""Joint limits on the final command (limits.py) and validated, immutable configuration."""
import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from skinsafe.core.safety.limits import JointLimits, brake, final_command, scale_into
from skinsafe.core.safety.retraction import RetractionParams

LIM = JointLimits(np.full(6, np.pi), np.full(6, 15.0), 0.002)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), mag=st.sampled_from([0.0, 1e-3, 1.0, 1e3, 1e12]),
       dt=st.sampled_from([1e-4, 2e-3, 8e-3]))
def test_scale_into_keeps_direction_and_bounds(seed, mag, dt):
    rng = np.random.default_rng(seed)
    lim = JointLimits(np.full(6, np.pi), np.full(6, 15.0), dt)
    want = rng.normal(size=6) * mag
    out = scale_into(want, np.zeros(6), lim)
    assert np.all(np.abs(out) <= lim.vel * (1 + 1e-12)) and np.all(np.abs(out) <= lim.acc * dt * (1 + 1e-12))
    if mag > 0:  # from rest the direction is kept exactly
        assert np.allclose(np.cross(out[:3], want[:3]), 0, atol=1e-9 * mag) and out @ want >= 0


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), K=st.integers(1, 12), speed=st.sampled_from([0.1, 1.0, 3.0]))
def test_final_command_projects_onto_limits_and_no_push_rows(seed, K, speed):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(K, 6))
    prev = rng.uniform(-1, 1, 6) * speed
    prev = np.clip(prev, -LIM.vel, LIM.vel)
    v = rng.normal(size=6) * speed
    res = final_command(v, prev, LIM, A, np.zeros(K))
    vel, acc = LIM.violations(res.v, prev)
    assert not vel and not acc
    if not res.infeasible:
        assert np.all(A @ res.v >= -1e-6)
    lo, hi = LIM.box(prev)
    inside = np.clip(v, lo, hi)
    if np.all(A @ inside >= 0) and np.array_equal(inside, v):
        assert np.array_equal(res.v, v) and not res.changed  # a feasible command passes untouched


def test_brake_slows_every_joint_at_its_limit_and_stops():
    prev = np.array([1.0, -0.02, 0.0, 3.0, -3.0, 0.01])
    out = brake(prev, LIM)
    assert np.allclose(out, [0.97, 0.0, 0.0, 2.97, -2.97, 0.0])
    v = prev
    for _ in range(200):
        v = brake(v, LIM)
    assert np.array_equal(v, np.zeros(6))
    assert np.array_equal(brake(np.array([np.nan, 1.0, 0, 0, 0, 0]), LIM)[0], 0.0)


@pytest.mark.parametrize("kw,match", [
    ({"vel": [1.0, -1.0], "acc": [1.0, 1.0], "dt": 0.002}, "'vel' must be positive"),
    ({"vel": [1.0, 1.0], "acc": [0.0, 1.0], "dt": 0.002}, "'acc' must be positive"),
    ({"vel": [1.0, 1.0], "acc": [1.0, 1.0, 1.0], "dt": 0.002}, "one value per joint"),
    ({"vel": [1.0, 1.0], "acc": [1.0, 1.0], "dt": 0.0}, "'dt' is 0.0"),
    ({"vel": [1.0, 1.0], "acc": [1.0, 1.0], "dt": None}, "'dt' is None; it must be the positive control period"),
    ({"vel": [np.inf, 1.0], "acc": [1.0, 1.0], "dt": 0.002}, "'vel' must be positive finite"),
])
def test_limits_refused_with_what_to_change(kw, match):
    with pytest.raises(ValueError, match=match):
        JointLimits(**kw)


def test_configuration_is_immutable():
    with pytest.raises(dataclasses.FrozenInstanceError):
        LIM.dt = 0.0
    with pytest.raises(ValueError):
        LIM.vel[0] = 100.0
    p = RetractionParams()
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.T = 0.0
    with pytest.raises(TypeError):
        p.stimulus_alpha["force"] = -1.0
    with pytest.raises(ValueError, match="'alpha' is -0.1"):
        RetractionParams(alpha=-0.1)
    with pytest.raises(ValueError, match="'epsilon' is 1.5"):
        dataclasses.replace(p, epsilon=1.5)

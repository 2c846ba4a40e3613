"""The defensiveness layer on the UR5 sample skin: eq. 10 tracking, pool, priorities, limits,
outranking the plan, and the numerical extremes of issue 5 (property-based)."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from skinsafe.core.bench.retraction import rows as bench_rows
from skinsafe.core.design.sample import design_with, make_sample_design
from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.safety.defensiveness import DefensivenessLayer
from skinsafe.core.safety.retraction import RetractionParams

ROBOT = build_ur5()
DESIGN = make_sample_design("ur5", robot=ROBOT)
KIN = TaxelKinematics(ROBOT.model, DESIGN)
N, DT = DESIGN.n_taxels, 0.002
# UR5 singular configurations: stretched up (shoulder + elbow + wrist at once), elbow straight,
# wrist_2 = 0 (wrist 1 and 3 axes aligned), wrist centre on the shoulder axis.
SINGULAR = {
    "all": np.array([0.0, -np.pi / 2, 0.0, -np.pi / 2, 0.0, 0.0]),
    "elbow": np.array([0.3, -1.0, 0.0, -1.2, -1.5, 0.0]),
    "wrist": np.array([0.0, -1.2, 1.6, -1.97, 0.0, 0.0]),
    "shoulder": np.array([0.0, -np.pi / 2, 0.0, 0.0, 1.2, 0.4]),
    "home": ROBOT.home,
}


def layer(**kw):
    return DefensivenessLayer(KIN, DESIGN.taxels.thresholds, ROBOT.vel_limits, ROBOT.acc_limits, RetractionParams(**kw),
                              DT)


def taxel_on(body: str, k: int = 0) -> int:
    return int(np.flatnonzero(DESIGN.taxels.body == DESIGN.bodies.index(body))[k])


def run(L, q, force, t_end, dt=0.002, planned=None, hold=0.0):
    """Integrate the layer's command kinematically; `force` is applied until `hold` seconds."""
    q = q.copy()
    qs, cmds, t = [q.copy()], [], 0.0
    while t < t_end - 1e-12:
        f = force if t <= hold else np.zeros(N)
        qd = L.tick(t, q, {"force": f}, planned, dt)
        q = q + qd * dt
        t += dt
        qs.append(q.copy())
        cmds.append(qd)
    return np.array(qs), np.array(cmds)


@pytest.mark.parametrize("body", ["forearm_link", "wrist_1_link", "wrist_3_link"])
def test_single_poke_follows_eq10(body):
    i = taxel_on(body, 40)
    L = layer(alpha=0.05, T=0.5)
    f = np.zeros(N)
    f[i] = 12.0
    p0, fr = (a.copy() for a in KIN.poses(ROBOT.home))
    z = fr[i, :, 2].copy()
    qs, cmds = run(L, ROBOT.home, f, 0.6)
    P = np.array([KIN.poses(q)[0][i].copy() for q in qs])
    along = (p0[i] - P) @ z
    want = 0.05 * 12.0 / 12  # 5 cm
    assert along[-1] == pytest.approx(want, rel=0.01)
    t = np.arange(len(qs)) * 0.002
    from skinsafe.core.safety.retraction import profile
    ref = 12 * want * profile((t - 0.002) / 0.5)  # the first tick (t=0) triggers; motion starts after it
    assert np.abs(along - ref).max() < 0.02 * want
    assert np.all(np.diff(along) >= -1e-9)  # never back toward the contact
    side = np.linalg.norm((P - p0[i]) + along[:, None] * z, axis=1)
    assert side.max() < 0.02 * want
    assert np.abs(cmds[-20:]).max() == 0.0  # retraction over, no plan: stands still
    assert not L.active


def test_peak_hold_priorities_and_retrigger():
    i, j = taxel_on("forearm_link", 10), taxel_on("wrist_2_link", 5)
    L = layer(alpha=0.01, T=0.2)
    f = np.zeros(N)
    f[i], f[j] = 3.0, 9.0
    L.tick(0.0, ROBOT.home, {"force": f})
    assert list(L.pool) == [j, i]  # heavier touch, higher priority
    assert np.allclose(L.priorities, [0.01 * 9 / 12, 0.01 * 3 / 12])
    f[i] = 30.0  # the force still rises after the threshold: peak held
    L.tick(0.002, ROBOT.home, {"force": f})
    assert list(L.pool) == [i, j] and np.allclose(L.desired_distance(), [0.01 * 30 / 12, 0.01 * 9 / 12])
    qs, _ = run(L, ROBOT.home, np.zeros(N), 0.18)
    assert not L.active or L.priorities.max() < 0.2 * 0.01 * 30 / 12  # priorities decay toward 0
    f[:] = 0
    f[i] = 5.0
    L.tick(0.21, qs[-1], {"force": f})  # still in danger after T: triggers again
    assert list(L.pool) == [i] and L.desired_distance()[0] == pytest.approx(0.01 * 5 / 12)


def test_outranks_the_plan_and_hands_back():
    plan = np.array([0.2, -0.1, 0.1, 0.0, 0.05, 0.0])
    L = layer(T=0.1)
    q = ROBOT.home
    for k in range(10):  # idle: the plan goes through (it is within the limits)
        out = L.tick(k * 0.002, q, {"force": np.zeros(N)}, plan)
    assert np.allclose(out, plan) and not L.active
    f = np.zeros(N)
    f[taxel_on("forearm_link", 3)] = 10.0
    ref = layer(T=0.1)  # the same retraction with no plan at all, from the same last command
    ref.last[:] = plan
    t0, dt = 0.02, 0.002
    a = [L.tick(t0, q, {"force": f}, plan)] + [L.tick(t0 + k * dt, q, {"force": 0 * f}, plan) for k in range(1, 40)]
    b = [ref.tick(0.0, q, {"force": f})] + [ref.tick(k * dt, q, {"force": 0 * f}) for k in range(1, 40)]
    assert L.active
    assert np.abs(a[0] - plan).max() <= ROBOT.acc_limits.max() * dt + 1e-12  # acceleration-limited switch
    assert np.allclose(a, b, atol=1e-12)  # the plan is ignored while retracting
    assert np.abs(a[-1]).max() > 0.01
    for k in range(60):
        out = L.tick(0.2 + k * 0.002, q, {"force": np.zeros(N)}, plan)
    assert not L.active and np.allclose(out, plan)


def _trigger_set(kind: str, k: int, rng) -> np.ndarray:
    fore = np.flatnonzero(DESIGN.taxels.body == DESIGN.bodies.index("forearm_link"))
    if kind == "random":
        return rng.choice(N, min(k, N), replace=False)
    if kind == "same_ring":  # all around one ring of a link: opposite normals included
        z = DESIGN.taxels.positions[fore, 2]
        ring = fore[np.abs(z - z[0]) < 1e-9]
        return ring[:k]
    if kind == "collinear":  # one column along the link: identical normals, collinear positions
        n = DESIGN.taxels.normals[fore]
        return fore[np.linalg.norm(n - n[0], axis=1) < 1e-9][:k]
    raise ValueError(kind)


@settings(max_examples=40, deadline=None)
@given(config=st.sampled_from(sorted(SINGULAR)), force=st.sampled_from([0.0, 2.5, 30.0, 1e3, 1e6]),
       T=st.sampled_from([0.02, 0.05, 0.5, 10.0]), alpha=st.sampled_from([0.0, 0.01, 0.05, 1e3]),
       eps=st.sampled_from([0.0, 1.0]), kind=st.sampled_from(["random", "same_ring", "collinear"]),
       k=st.sampled_from([1, 2, 3, 8, 64]), form=st.sampled_from(["3d", "6d"]), seed=st.integers(0, 1000),
       acc=st.sampled_from(["robot", "unbounded"]))
def test_extremes_stay_finite_limited_and_retract(config, force, T, alpha, eps, kind, k, form, seed, acc):
    """With the robot's acceleration limits a new command blends from the last one (a taxel
    cannot reverse instantly); the retraction law itself is checked with them unbounded."""
    rng = np.random.default_rng(seed)
    q0 = SINGULAR[config]
    idx = _trigger_set(kind, k, rng)
    acc_limits = ROBOT.acc_limits if acc == "robot" else np.full(6, 1e12)
    L = DefensivenessLayer(KIN, DESIGN.taxels.thresholds, ROBOT.vel_limits, acc_limits,
                           RetractionParams(alpha=alpha, T=T, epsilon=eps, form=form), DT)
    f = np.zeros(N)
    f[idx] = np.maximum(force * rng.uniform(0.5, 1.0, len(idx)), 2.5)  # all above the 2 N threshold
    dt, q, prev = 0.002, q0.copy(), np.zeros(6)
    ticks = min(40, int(np.ceil(T / dt)) + 2)
    t_mid = [0.0, T / 3] if T > 2 * dt else [0.0]
    for t in sorted(set(np.linspace(0, T, ticks).tolist() + t_mid)):
        qd = L.tick(t, q, {"force": f}, None, dt)
        assert np.all(np.isfinite(qd))
        assert np.all(np.abs(qd) <= ROBOT.vel_limits * (1 + 1e-9))
        assert np.all(np.abs(qd - prev) <= acc_limits * dt * (1 + 1e-9))
        if acc == "unbounded" and L.active:
            # the dominant taxel never moves toward its contact
            J0 = KIN.jacobians_of(L.pool[:1], q)[0]
            z0 = L._state[0, 6:9]
            assert z0 @ (J0[0, :3] @ qd) <= 1e-9 * (1 + np.abs(qd).max())
            if len(idx) == 1:  # a single contact: that taxel moves away or not at all
                assert L.retracted[0] >= -1e-9
        prev = qd
        q = q + qd * dt


def test_ten_thousand_triggered_taxels():
    design, robot = design_with(10_000, ROBOT)  # tiled: many identical taxels (same position and normal)
    kin = TaxelKinematics(robot.model, design)
    for eps in (0.0, 1.0):
        L = DefensivenessLayer(kin, design.taxels.thresholds, robot.vel_limits, robot.acc_limits,
                               RetractionParams(epsilon=eps, T=0.1), DT)
        f = {"force": np.linspace(3.0, 1e6, 10_000)}
        q = SINGULAR["all"].copy()
        for t in (0.0, 0.02, 0.04):
            qd = L.tick(t, q, f)
            assert np.all(np.isfinite(qd)) and np.all(np.abs(qd) <= robot.vel_limits * (1 + 1e-9))
            q = q + qd * 0.002
        assert len(L.pool) == 10_000


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="thresholds\\['force'\\] has shape \\(3,\\)"):
        DefensivenessLayer(KIN, {"force": np.ones(3)}, ROBOT.vel_limits, ROBOT.acc_limits, dt=DT)
    with pytest.raises(ValueError, match="'vel' must be positive finite numbers.*6 joints"):
        DefensivenessLayer(KIN, DESIGN.taxels.thresholds, -ROBOT.vel_limits, ROBOT.acc_limits, dt=DT)
    with pytest.raises(ValueError, match="give dt, the control period"):
        DefensivenessLayer(KIN, DESIGN.taxels.thresholds, ROBOT.vel_limits, ROBOT.acc_limits)
    with pytest.raises(ValueError, match="T = 0.01 s is under 10 control periods"):
        DefensivenessLayer(KIN, DESIGN.taxels.thresholds, ROBOT.vel_limits, ROBOT.acc_limits, RetractionParams(T=0.01),
                           DT)
    L = layer()
    plan = np.full(6, 0.5)
    assert np.array_equal(L.tick(0.0, ROBOT.home, {"force": np.zeros(N)}, plan), np.full(6, 15.0 * DT))
    # no force readings, or a cut-off array: missing data brakes (from 0.03 rad/s) and is flagged, never "no contact"
    for k, r in enumerate([{}, {"force": np.zeros(5)}, {"pressure": np.zeros(N)}], 1):
        assert np.allclose(L.tick(k * DT, ROBOT.home, r, plan), 0.0) and L.info.missing == ("force",) and L.info.safe
    assert L.flags["missing:force"] == L.flags["missing"] == 3


def test_other_stimuli_trigger_with_their_own_gain():
    i = taxel_on("wrist_1_link", 2)
    th = dict(DESIGN.taxels.thresholds, temperature=np.full(N, 45.0))
    L = DefensivenessLayer(KIN, th, ROBOT.vel_limits, ROBOT.acc_limits, RetractionParams(), DT)
    temp = np.full(N, 25.0)
    temp[i] = 60.0
    L.tick(0.0, ROBOT.home, {"force": np.zeros(N), "temperature": temp})
    assert list(L.pool) == [i]
    assert L.desired_distance()[0] == pytest.approx(max(0.002 * 60.0, 0.0) / 12)


def test_bench_rows_agree_with_loop():
    out = bench_rows(type("A", (), {"taxels": 512, "active": "1,8,40", "repeat": 3, "epsilon": 1.0})())
    assert [r["active"] for r in out] == [1, 8, 40]
    assert all(set(r) >= {"active", "n_taxels", "ms", "speedup_vs_loop"} for r in out)
    assert max(r["max_abs_diff"] for r in out) < 1e-12

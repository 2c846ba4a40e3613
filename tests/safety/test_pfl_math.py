"""PFL: the ISO/TS 15066 table against its second sources, the effective mass against MuJoCo's own
response to an impulse, v_max against the closed form, and the speed cap's guarantee on every
taxel (UR5 and Panda, random poses and commands)."""
import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.robot.models import build_panda, build_ur5
from skinsafe.core.safety import pfl


@pytest.fixture(scope="module", params=["ur5", "panda"])
def setup(request):
    robot = build_ur5() if request.param == "ur5" else build_panda()
    design = make_sample_design(request.param, pitch=0.02, robot=robot)
    return robot, design, TaxelKinematics(robot.model, design)


def test_table_matches_second_sources():
    # transient limits of ISO 10218-2:2025 Annex A (safety.stimba.sk/en/pfl): twice the quasi-static ones
    stimba = {"back": 420, "chest": 280, "abdomen": 220, "pelvis": 360, "upper_arm": 300, "lower_arm": 320, "hand": 280}
    for name, ft in stimba.items():
        assert pfl.region(name).transient_N == ft
    # spring constants (N/mm) listed from ISO/TS 15066 Table A.2 (inmotion)
    for name, k in {"skull": 150, "face": 75, "neck": 50, "back": 35, "chest": 25, "abdomen": 10}.items():
        assert pfl.region(name).k_N_per_m == 1e3 * k
    assert pfl.region("skull").transient_N is None and pfl.region("face").transient_N is None
    assert pfl.region("back").mass_kg == 40 and pfl.region("hand").mass_kg == 0.6
    with pytest.raises(ValueError, match="unknown; use one of"):
        pfl.region("elbow")


def test_v_max_closed_form():
    for reg in pfl.REGIONS.values():
        for m_r in (0.5, 3.0, 20.0, np.inf):
            mu = 1 / (1 / reg.mass_kg + 1 / m_r)
            want = reg.transient_limit() / np.sqrt(mu * reg.k_N_per_m)
            assert np.isclose(pfl.v_max(reg, 1 / m_r), want, rtol=1e-12)
    # the example numbers: a 2 kg lower arm (k 40 N/mm, 320 N) against a 8 kg robot
    assert np.isclose(pfl.v_max("lower_arm", 1 / 8.0), 320 / np.sqrt(1.6 * 40e3))
    assert pfl.v_max("face", 0.1) == 0.0  # no transient contact with the face


def _impulse_mass(model, q, taxel_pos, body, normal, impulse=1e-3):
    """The effective mass MuJoCo shows: a tiny force along the normal at the taxel for one step
    (gravity, contacts, actuation and damping off), m = impulse / (normal velocity change)."""
    m = model.__copy__()
    m.opt.disableflags |= (mujoco.mjtDisableBit.mjDSBL_GRAVITY | mujoco.mjtDisableBit.mjDSBL_CONTACT
                           | mujoco.mjtDisableBit.mjDSBL_ACTUATION | mujoco.mjtDisableBit.mjDSBL_DAMPER
                           | mujoco.mjtDisableBit.mjDSBL_SPRING)
    m.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
    d = mujoco.MjData(m)
    d.qpos[:] = q
    mujoco.mj_forward(m, d)
    h = m.opt.timestep
    mujoco.mj_applyFT(m, d, normal * impulse / h, np.zeros(3), taxel_pos, body, d.qfrc_applied)
    mujoco.mj_step(m, d)
    jp = np.zeros((3, m.nv))
    d0 = mujoco.MjData(m)
    d0.qpos[:] = q
    mujoco.mj_forward(m, d0)
    mujoco.mj_jac(m, d0, jp, None, taxel_pos, body)
    return impulse / float(normal @ jp @ d.qvel)


@settings(max_examples=8, deadline=None)
@given(st.integers(0, 10 ** 6))
def test_effective_mass_matches_impulse_response(setup, seed):
    robot, design, kin = setup
    rng = np.random.default_rng(seed)
    q = robot.home + rng.uniform(-0.6, 0.6, robot.model.nq)
    m_r = pfl.effective_mass(kin, q)
    pos, frames = kin.poses(q)
    moving = np.flatnonzero(m_r < 1e3)
    for i in rng.choice(moving, 6, replace=False):
        got = _impulse_mass(robot.model, q, pos[i].copy(), int(kin.body_id[i]), frames[i, :, 2].copy())
        assert np.isclose(m_r[i], got, rtol=2e-3), (i, m_r[i], got)


def test_normal_rows_match_taxel_jacobians(setup):
    robot, design, kin = setup
    q = robot.home + 0.3
    rows = pfl.NormalRows(kin)(q).copy()
    J, _, frames = kin.jacobians(q)
    assert np.allclose(rows, np.einsum("nij,ni->nj", J[:, :3], frames[:, :, 2]), atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10 ** 6), st.floats(0.05, 20.0), st.sampled_from(["hand", "chest", "neck", "abdomen"]),
       st.floats(0.3, 1.0))
def test_cap_holds_on_every_taxel(setup, seed, speed, reg, factor):
    robot, design, kin = setup
    rng = np.random.default_rng(seed)
    q = robot.home + rng.uniform(-1, 1, robot.model.nq)
    v = rng.normal(size=robot.model.nv) * speed
    cap = pfl.PFLCap(kin, (reg, "lower_arm"), factor=factor)
    out = cap(q, v)
    J, _, frames = kin.jacobians(q)
    vn = np.einsum("nij,ni,j->n", J[:, :3], frames[:, :, 2], out)
    inv = 1 / pfl.effective_mass(kin, q)
    vm = factor * np.minimum(pfl.v_max(reg, inv), pfl.v_max("lower_arm", inv))
    assert np.all(vn <= vm + 1e-9)
    assert np.allclose(out, cap.last_scale * v) and 0 <= cap.last_scale <= 1
    if cap.last_scale < 1:  # the binding taxel sits exactly at its limit: no needless slowing
        assert np.isclose(vn[cap.last_taxel], vm[cap.last_taxel], rtol=1e-9)


def test_cap_fails_safe(setup):
    robot, design, kin = setup
    cap = pfl.PFLCap(kin, "hand")
    q, v = robot.home.copy(), np.ones(robot.model.nv)
    for bad_q, bad_v in ((np.r_[np.nan, q[1:]], v), (q, np.r_[np.inf, v[1:]])):
        assert np.array_equal(cap(bad_q, bad_v), np.zeros_like(v))
    assert cap.flags == 2
    assert np.array_equal(pfl.PFLCap(kin, "face")(q, v), np.zeros_like(v))  # face: no approach speed at all
    with pytest.raises(ValueError, match="factor"):
        pfl.PFLCap(kin, "hand", factor=1.5)


def test_stack_applies_cap_after_modulation(setup):
    from skinsafe.core.safety.stack import SafetyStack

    robot, design, kin = setup
    cap = pfl.PFLCap(kin, "chest")
    stack = SafetyStack(robot.vel_limits, pfl=cap, dt=0.002)
    v = stack.tick(0.0, robot.home, None, robot.vel_limits * 0.9, 0.002)
    assert 0 < cap.last_scale < 1 and np.allclose(v, cap.last_scale * robot.vel_limits * 0.9)


def test_bench_reference_agrees_with_the_cap(setup):
    from skinsafe.core.bench.pfl import loop_cap

    robot, design, kin = setup
    rng = np.random.default_rng(3)
    for _ in range(3):
        q, v = robot.home + rng.uniform(-1, 1, robot.model.nq), rng.normal(size=robot.model.nv) * 3
        assert np.allclose(pfl.PFLCap(kin, ("hand", "chest"))(q, v), loop_cap(kin, ("hand", "chest"), q, v), atol=1e-12)


def test_pressure_table_matches_the_specific_body_areas():
    """Table A.2's pressures per specific body area (N/cm^2, as listed in ISO/TS 15066 and repeated in
    public PFL code); a region takes its lowest area; transient is twice that, none for the head."""
    areas = {"skull": (130, 110), "face": (110,), "neck": (140, 210), "back": (160, 210), "chest": (120, 170),
             "abdomen": (140,), "pelvis": (210,), "upper_arm": (190, 220), "lower_arm": (190, 180, 180),
             "hand": (300, 270, 280, 220, 200, 260, 200, 190), "thigh": (250, 220), "lower_leg": (220, 210)}
    assert set(areas) == set(pfl.REGIONS)
    for name, values in areas.items():
        reg = pfl.region(name)
        assert reg.pressure_N_cm2 == min(values)
        assert reg.pressure_limit("clamp") == reg.pressure_limit("quasi_static") == min(values)
        assert reg.pressure_limit("transient") == (0 if reg.transient_N is None else 2 * min(values))
        assert reg.force_limit("clamp") == reg.quasi_static_N and reg.force_limit("transient") == reg.transient_limit()
    with pytest.raises(ValueError, match="contact kind"):
        pfl.region("hand").force_limit("impact")


def _reference_bounds(kin, q, regions, factor, area, plane, gap, stop_s, parts=()):
    """The cap's bound on every taxel's normal speed, taxel by taxel from the module's formulas
    (world poses and effective masses from `TaxelKinematics` and `effective_mass`)."""
    pos, frames = kin.poses(q)
    inv = 1.0 / pfl.effective_mass(kin, q)
    o, u = plane
    out = np.full(kin.n, np.inf)
    for i in range(kin.n):
        n = frames[i, :, 2]
        clamp = n @ u < -0.5 and 0 <= (pos[i] - o) @ u <= gap

        def limit(reg, dist):
            r = pfl.region(reg)
            if clamp:
                f = min(r.quasi_static_N, 1e4 * r.pressure_N_cm2 * area[i])
                return 0.0 if inv[i] <= 0 else factor * (f / r.k_N_per_m) / (1 / np.sqrt(inv[i] * r.k_N_per_m) + stop_s)
            if r.transient_N is not None:
                f = min(r.transient_N, 2e4 * r.pressure_N_cm2 * area[i])
                return factor * f / np.sqrt(r.k_N_per_m) * np.sqrt(1 / r.mass_kg + inv[i])
            return 2.0 * (dist - 0.1) if np.isfinite(dist) else 0.0

        if not parts:
            out[i] = min(limit(r, np.inf) for r in regions)
        for reg, a, b, rad, vel in parts:
            ab = b - a
            s = np.clip((pos[i] - a) @ ab / max(ab @ ab, 1e-300), 0, 1) if ab @ ab > 0 else 0.0
            c = a + s * ab
            dist = np.linalg.norm(pos[i] - c) - rad
            if dist > 0.3 or (c - pos[i]) @ n < np.cos(np.pi / 4) * np.linalg.norm(c - pos[i]):
                continue
            out[i] = min(out[i], (-0.2 if dist <= 0.0 else limit(reg, dist)) + n @ vel)
    return out, frames


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10 ** 6), st.floats(0.1, 6.0), st.floats(0.3, 1.0), st.floats(-0.3, 0.4))
def test_cap_with_pressure_and_clamping_holds_on_every_taxel(setup, seed, speed, factor, table_z):
    """Per-taxel contact areas (pressure) and a table below the arm (clamping): every taxel's normal
    speed within its bound, checked against the formulas taxel by taxel."""
    robot, design, kin = setup
    rng = np.random.default_rng(seed)
    q = robot.home + rng.uniform(-1, 1, robot.model.nq)
    v = rng.normal(size=robot.model.nv) * speed
    area = rng.uniform(0.2e-4, 3e-4, kin.n)
    plane = (np.array([0, 0, table_z]), np.array([0, 0, 1.0]))
    cap = pfl.PFLCap(kin, ("hand", "chest"), factor=factor, area=area, fixtures=[plane], clamp_gap=0.12, stop_s=0.02)
    out = cap(q, v)
    bound, frames = _reference_bounds(kin, q, ("hand", "chest"), factor, area, plane, 0.12, 0.02)
    assert np.allclose(cap.bound, bound, rtol=1e-9, atol=1e-12)
    J, _, frames = kin.jacobians(q)
    vn = np.einsum("nij,ni,j->n", J[:, :3], frames[:, :, 2], out)
    assert np.all(vn <= bound + 1e-9)
    assert np.allclose(out, cap.last_scale * v) and 0 <= cap.last_scale <= 1  # all bounds >= 0: scaled
    assert cap.clamp.any() == bool((bound < np.inf).any() and cap.clamp.any())


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10 ** 6), st.floats(0.0, 3.0), st.floats(0.0, 1.5), st.sampled_from(["hand", "lower_arm", "face"]))
def test_cap_uses_the_relative_velocity_of_the_near_parts(setup, seed, speed, part_speed, reg):
    """A body part near the arm, moving: every taxel in reach and in front of it meets
    `a_i . qdot - n_i . v_part <= v_max` (the robot backs away when the part closes in faster than
    allowed, or when the face is inside the keep-out), taxels out of reach are left free."""
    robot, design, kin = setup
    rng = np.random.default_rng(seed)
    q = robot.home + rng.uniform(-0.8, 0.8, robot.model.nq)
    pos, _ = kin.poses(q)
    centre = pos[rng.integers(kin.n)] + rng.normal(0, 0.08, 3)
    a, b = centre - [0.05, 0, 0], centre + [0.05, 0, 0]
    vel = rng.normal(size=3) * part_speed
    cap = pfl.PFLCap(kin, (reg,), factor=0.8)
    cap.observe(pfl.Person((reg,), a[None], b[None], np.array([0.04]), vel[None]))
    v = rng.normal(size=robot.model.nv) * speed
    out = cap(q, v)
    bound, frames = _reference_bounds(kin, q, (reg,), 0.8, np.full(kin.n, np.inf), (np.zeros(3), np.array([0, 0, 1.0])),
                                      -1.0, 0.02, parts=[(reg, a, b, 0.04, vel)])
    assert np.allclose(cap.bound, bound, rtol=1e-9, atol=1e-12)
    J, _, frames = kin.jacobians(q)
    vn = np.einsum("nij,ni,j->n", J[:, :3], frames[:, :, 2], out)
    if cap.last_mode == "stop":  # no command meets every bound (parts on both sides): a stop, counted
        assert cap.failed and np.array_equal(out, np.zeros_like(v))
    else:
        assert np.all(vn <= bound + 1e-6)
    assert cap.last_mode != "retreat" or (bound < 0).any()


def test_face_is_avoided_not_frozen_at(setup):
    """A face with v_max = 0: unobserved, the cap can only stop the robot; observed far from the arm,
    it leaves the command alone; inside the keep-out it moves the near taxels away from it, even
    from a still command."""
    robot, design, kin = setup
    q = robot.home.copy()
    v = np.linspace(0.5, -0.5, robot.model.nv)
    assert np.array_equal(pfl.PFLCap(kin, "face")(q, v), np.zeros_like(v))
    cap = pfl.PFLCap(kin, "face")
    pos, frames = kin.poses(q)
    far = pos.mean(axis=0) + [0, 0, 2.0]
    cap.observe(pfl.Person(("face",), far[None], far[None], np.array([0.1]), np.zeros((1, 3))))
    assert np.array_equal(cap(q, v), v) and cap.last_mode == "free"
    i = int(np.argmax(pos[:, 2]))  # a taxel on top, facing up: the face 5 cm above it
    face = pos[i] + frames[i, :, 2] * 0.15
    cap.observe(pfl.Person(("face",), face[None], face[None], np.array([0.1]), np.zeros((1, 3))))
    out = cap(q, np.zeros(robot.model.nv))
    J, _, frames = kin.jacobians(q)
    vn = np.einsum("nij,ni,j->n", J[:, :3], frames[:, :, 2], out)
    near = np.isfinite(cap.bound) & (cap.bound < 0)
    assert cap.last_mode == "retreat" and near[i] and np.all(vn[near] <= cap.bound[near] + 1e-6) and vn[i] < 0

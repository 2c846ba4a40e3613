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

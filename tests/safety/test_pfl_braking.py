"""The PFL cap's braking model (`PFLCap(..., acc=, stop_s=, lag_s=)`): near a body part, every taxel's command lets
the arm, reacting tau = stop_s + lag_s late (from its measured speed where that is the faster) and then braking the
command as a whole at the joint acceleration limits, stop within the distance to the part plus what a lag-free arm
meeting the part at v_max covers braking (UR5, random poses, commands, measured velocities, parts and distances)."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.safety import pfl

ACC = np.array([15.0, 15.0, 15.0, 25.0, 25.0, 25.0])
FACTOR = 0.8


@pytest.fixture(scope="module")
def ur5():
    robot = build_ur5()
    design = make_sample_design("ur5", pitch=0.02, robot=robot)
    return robot, TaxelKinematics(robot.model, design)


def _reference(kin, q, v, qdot, reg, a, b, radius, vel, tau):
    """Per taxel from the formulas (module docstring of core.safety.pfl): the bound on its normal speed (inf: no
    part near; NaN: at the edge of the reach or of 45 degrees, within rounding), its deceleration when the command brakes as a whole, its distance to the part, v_max, and the
    normal speeds of the command and of the arm."""
    pos, frames = kin.poses(q)
    J, _, frames = kin.jacobians(q)
    n = frames[:, :, 2]
    u = np.einsum("nij,ni,j->n", J[:, :3], n, v)
    um = np.einsum("nij,ni,j->n", J[:, :3], n, qdot)
    vm = FACTOR * pfl.v_max(reg, 1.0 / pfl.effective_mass(kin, q))
    h = np.max(np.abs(v) / ACC)
    bound, dist, dec = np.full(kin.n, np.inf), np.full(kin.n, np.inf), np.maximum(u, 0.0) / h
    edge = np.zeros(kin.n, bool)  # within rounding of the reach or of 45 degrees: either side is right
    for i in range(kin.n):
        ab = b - a
        c = a + np.clip((pos[i] - a) @ ab / (ab @ ab), 0, 1) * ab if ab @ ab > 0 else a
        d = np.linalg.norm(pos[i] - c) - radius
        front = (c - pos[i]) @ n[i] - np.cos(np.pi / 4) * np.linalg.norm(c - pos[i])
        edge[i] = abs(d - 0.3) < 1e-9 or abs(front) < 1e-9
        if d > 0.3 or front < 0:
            continue
        dist[i] = d
        if d <= 0:
            lim = -0.2
        elif u[i] <= 0:
            lim = vm[i]
        else:
            lim = -dec[i] * tau + np.sqrt((dec[i] * tau) ** 2 + vm[i] ** 2 + 2 * dec[i] * d)
            if um[i] > lim:
                lim = np.sqrt(max(vm[i] ** 2 + 2 * dec[i] * (d - tau * um[i]), 0.0))
        bound[i] = lim + n[i] @ vel
    bound[edge] = np.nan
    return bound, dec, dist, vm, um, J, n


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10 ** 6), st.floats(0.2, 4.0), st.floats(0.0, 1.5), st.floats(0.005, 0.25),
       st.floats(0.02, 0.1), st.sampled_from(["hand", "lower_arm", "chest"]))
def test_every_near_taxel_can_stop_within_the_distance_to_a_still_part(ur5, seed, speed, lag, gap, tau, reg):
    robot, kin = ur5
    rng = np.random.default_rng(seed)
    q = robot.home + rng.uniform(-0.8, 0.8, robot.model.nq)
    pos, frames = kin.poses(q)
    i = rng.integers(kin.n)
    a = b = pos[i] + frames[i, :, 2] * (gap + 0.04)  # a ball `gap` in front of taxel i
    v = rng.normal(size=robot.model.nv) * speed
    qdot = v * (1 + lag * rng.uniform(0, 1, robot.model.nv))  # the arm, lagging a braking command, faster than it
    cap = pfl.PFLCap(kin, (reg,), factor=FACTOR, stop_s=0.02, acc=ACC, lag_s=tau - 0.02)
    cap.observe(pfl.Person((reg,), a[None], b[None], np.array([0.04]), np.zeros((1, 3))))
    out = cap(q, v, qdot)
    bound, dec, dist, vm, um, J, n = _reference(kin, q, v, qdot, reg, a, b, 0.04, np.zeros(3), tau)
    ok = ~np.isnan(bound)
    assert np.allclose(cap.bound[ok], bound[ok], rtol=1e-9, atol=1e-12) and np.isfinite(bound[i])
    bound = cap.bound
    u = np.einsum("nij,ni,j->n", J[:, :3], n, out)
    if cap.last_mode == "retreat":  # a taxel beside i touches the part: it gives way, the others within bounds
        assert (dist <= 0).any() and np.all(u[np.isfinite(bound)] <= bound[np.isfinite(bound)] + 1e-6)
        return
    near = np.isfinite(bound) & (dec > 0)
    u, um, dec, dist, vm = u[near], um[near], dec[near], dist[near], vm[near]
    allowed = dist + vm ** 2 / (2 * dec)
    moving = u > 1e-9
    travel = tau * np.maximum(u, um) + u ** 2 / (2 * dec)  # reaction, then braking
    assert np.all(travel[moving] <= allowed[moving] * (1 + 1e-9) + 1e-12)
    assert np.all(u[tau * um > allowed] <= 1e-9)  # an arm that cannot stop in time whatever it is sent: not along


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10 ** 6), st.floats(0.2, 4.0), st.floats(0.0, 1.5))
def test_a_moving_part_and_an_unseen_person(ur5, seed, speed, part_speed):
    """A moving part: the bounds are the formulas' (its velocity included). The person unseen (every region
    anywhere, at distance 0): the braking model only lowers the cap. The acceleration limits are validated."""
    robot, kin = ur5
    rng = np.random.default_rng(seed)
    q = robot.home + rng.uniform(-0.8, 0.8, robot.model.nq)
    pos, _ = kin.poses(q)
    centre = pos[rng.integers(kin.n)] + rng.normal(0, 0.08, 3)
    a, b, vel = centre - [0.05, 0, 0], centre + [0.05, 0, 0], rng.normal(size=3) * part_speed
    v = rng.normal(size=robot.model.nv) * speed
    braking, plain = pfl.PFLCap(kin, "hand", factor=FACTOR, stop_s=0.02, acc=ACC, lag_s=0.06), pfl.PFLCap(kin, "hand", factor=FACTOR)
    braking(q, v, v), plain(q, v, v)
    assert np.all(braking.bound <= plain.bound + 1e-12) and (braking.bound < plain.bound - 1e-6).any()
    braking.observe(pfl.Person(("hand",), a[None], b[None], np.array([0.04]), vel[None]))
    braking(q, v, v)
    ref = _reference(kin, q, v, v, "hand", a, b, 0.04, vel, 0.08)[0]
    assert np.allclose(braking.bound[~np.isnan(ref)], ref[~np.isnan(ref)], rtol=1e-9, atol=1e-12)
    for bad in (0.0, -1.0, np.nan, np.full(3, 15.0)):
        with pytest.raises(ValueError, match="acc"):
            pfl.PFLCap(kin, "hand", acc=bad)

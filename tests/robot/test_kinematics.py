"""Batched taxel Jacobians against central finite differences of forward kinematics."""
import numpy as np
import pytest

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.kinematics import TaxelKinematics, retractability
from skinsafe.core.robot.models import build_panda, build_ur5


def _fd_jacobian(kin, q, h=1e-6):
    n, nv = kin.n, len(q)
    J = np.zeros((n, 6, nv))
    for k in range(nv):
        dq = np.zeros(nv)
        dq[k] = h
        p1, R1 = (a.copy() for a in kin.poses(q + dq))
        p0, R0 = (a.copy() for a in kin.poses(q - dq))
        J[:, :3, k] = (p1 - p0) / (2 * h)
        W = np.einsum("nij,nkj->nik", R1, R0)  # R1 R0^T = exp(2h [w]x)
        J[:, 3:, k] = np.stack([W[:, 2, 1] - W[:, 1, 2], W[:, 0, 2] - W[:, 2, 0], W[:, 1, 0] - W[:, 0, 1]], 1) / (4 * h)
    return J


@pytest.mark.parametrize("builder,name", [(build_ur5, "ur5"), (build_panda, "panda")])
def test_jacobians_match_finite_differences(builder, name):
    robot = builder()
    design = make_sample_design(name, robot=robot)
    rng = np.random.default_rng(1)
    keep = np.sort(rng.choice(design.n_taxels, 300, replace=False))
    kin = TaxelKinematics(robot.model, design.with_taxels(design.taxels.subset(keep)))
    lo, hi = robot.model.jnt_range[:, 0], robot.model.jnt_range[:, 1]
    for _ in range(3):
        q = rng.uniform(np.maximum(lo, -3), np.minimum(hi, 3))
        J = kin.jacobians(q)[0].copy()
        err = np.abs(J - _fd_jacobian(kin, q)).max()
        assert err < 1e-6, err
        assert np.abs(J - kin.jacobians_loop(q)).max() < 1e-12


def test_world_frames_orthonormal_and_positions_follow_body():
    robot = build_ur5()
    design = make_sample_design("ur5", robot=robot)
    kin = TaxelKinematics(robot.model, design)
    pos, frames = kin.poses(robot.home + 0.4)
    RtR = np.einsum("nji,njk->nik", frames, frames)
    assert np.abs(RtR - np.eye(3)).max() < 1e-12
    assert np.allclose(np.linalg.det(frames), 1.0)
    # a taxel sits at the link radius from its capsule axis: the upper-arm skin is 5 cm from the tube axis
    d = kin.data
    on = design.taxels.body == design.bodies.index("upper_arm_link")
    bid = robot.model.body("upper_arm_link").id
    R, o = d.xmat[bid].reshape(3, 3), d.xpos[bid]
    local = (pos[on] - o) @ R  # back in the body frame
    axis_dist = np.hypot(local[:, 1], local[:, 2] - 0.13585)
    assert np.allclose(axis_dist, 0.05, atol=1e-9)


def test_interleaved_bodies_give_the_same_jacobians():
    robot = build_ur5()
    design = make_sample_design("ur5", robot=robot)
    perm = np.random.default_rng(2).permutation(design.n_taxels)
    q = robot.home + 0.2
    J_sorted = TaxelKinematics(robot.model, design).jacobians(q)[0][perm]
    J_perm = TaxelKinematics(robot.model, design.with_taxels(design.taxels.subset(perm))).jacobians(q)[0]
    assert np.abs(J_sorted - J_perm).max() < 1e-14


def test_retractability_is_norm_of_jacobian_along_normal():
    """Retractability is |J_p^T z| per taxel."""
    robot = build_ur5()
    design = make_sample_design("ur5", robot=robot)
    kin = TaxelKinematics(robot.model, design)
    J, pos, frames = kin.jacobians(robot.home)
    r = retractability(J, frames)
    assert r.shape == (design.n_taxels,) and (r >= 0).all() and r.max() > 0.3
    # Manual value for one taxel: |J_p^T z|
    i = 123
    assert np.isclose(r[i], np.linalg.norm(J[i, :3].T @ frames[i][:, 2]))

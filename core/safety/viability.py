"""Viability of a command toward the contacted taxels (discrete time, as Del Prete 2018 does for
joint bounds): a command is accepted only if, from the velocity it leaves, a braking sequence
within the acceleration limits exists that moves no contacted taxel into its contact.

The no-push rows `a_k . qd >= b_k` (`a_k = -J_p,k(q)^T z_k`, z_k the taxel's normal when it was
touched) hold at this tick's q only. While the arm moves, each a_k turns with q; an arm that built
up speed (a retraction at its velocity limits) may then face a tick where no command within the
acceleration limits meets the turned rows (`infeasible`), and it pushes a taxel in for as long as
it takes to brake. The rows below keep it able to stop.

The braking sequence. From the command v, every joint slows toward 0 in proportion (the joint
that needs longest, `N = ceil(max_j |v_j| / (acc_j dt))` ticks, at its limit): the velocity stays
parallel to v, so the arm moves along the straight joint-space segment `q + s v`, s in [0, S],
`S = dt (N + 1) / 2`, and taxel k's speed along its retraction axis is a positive multiple of
`g_k(s) = a_k(q + s v) . v`. The sequence pushes no contacted taxel in when g_k >= 0 on [0, S].

Second order in s: `g_k(s) = a_k . v + s c_k(v)`, `c_k(v) = w_k(v) . v`,
`w_k(v) = d(a_k . v)/dq = -Jdot_k(q, v)^T z_k` (the taxel's curvature along its axis at joint
velocity v). Linear in s, so g_k >= 0 on [0, S] when it holds at both ends: s = 0 is the no-push
row; s = S is the viability row `a_k . v + S(v) c_k(v) >= 0`. That is quadratic in v (and S
depends on v); it is linearised at the velocity the tick starts from (v_ref, the last command or
the measured velocity; the command is within one tick's acceleration of it):

    (a_k + 2 S w_k + c_k dS/dv) . v >= S c_k + c_k (dS/dv . v_ref)     (c_k <= 0 in the dS term)

with w_k, c_k, S at v_ref (the tangent, not the secant `a_k(q + S v_ref)`: the secant ignores
how S c_k grows with the command, and measured over 1,200 random contact sets it let the rows
fall infeasible 2-3x as often). Rows the whole acceleration box already meets are dropped (they
cannot bind), so a DAQP level only sees the rows that matter.

`Jdot_k(q, v)` comes from the taxel's own 6 x nv Jacobian (hinge and slide joints, dofs numbered
from the base out as MuJoCo does): column i is `Omega_i x J_i + omega_i x P_i` with
`Omega_i = sum_{j<=i} v_j omega_j` and `P_i = sum_{j>i} v_j J_j` (omega_j the angular rows): no
second forward-kinematics pass (`tests/safety/test_viability.py` checks it against finite
differences of MuJoCo's Jacobians).
"""
from __future__ import annotations

import mujoco
import numba
import numpy as np


def check_joints(model: mujoco.MjModel) -> None:
    """The curvature formula needs hinge and slide joints; a ball or free joint is refused."""
    bad = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or str(j) for j in range(model.njnt)
           if int(model.jnt_type[j]) not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))]
    if bad:
        raise ValueError(f"viability: joints {bad} are ball or free joints; the retraction's viability rows "
                         "need hinge and slide joints (model the robot's joints as revolute or prismatic)")


def viability_rows(J: np.ndarray, order: np.ndarray, z: np.ndarray, A: np.ndarray, v_ref: np.ndarray,
                   lo: np.ndarray, hi: np.ndarray, acc: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The viability rows `V qd >= c` (module docstring) of the pool's taxels that can bind.

    J (K', 6, nv): the taxels' Jacobians; `order` (K,): the pool's taxels, highest priority first,
    as rows of J; z (K, 3): their normals when touched; A (K, nv): their no-push rows (same order);
    `v_ref` the velocity the tick starts from; lo, hi the tick's box; acc the acceleration limits."""
    return _rows(np.ascontiguousarray(J, dtype=np.float64), np.ascontiguousarray(order, dtype=np.intp),
                 np.ascontiguousarray(z, dtype=np.float64), np.ascontiguousarray(A, dtype=np.float64),
                 np.ascontiguousarray(v_ref, dtype=np.float64), lo, hi, np.ascontiguousarray(acc, dtype=np.float64),
                 float(dt))


@numba.njit(cache=True, nogil=True)
def _rows(J, order, z, A, v, lo, hi, acc, dt):
    K, nv = A.shape
    V, c = np.zeros((K, nv)), np.zeros(K)
    ratio, js = 0.0, 0
    for j in range(nv):
        r = abs(v[j]) / (acc[j] * dt)  # 0 where acc is infinite: stops within the tick
        if r > ratio:
            ratio, js = r, j
    N = np.ceil(ratio) + 1.0  # the ticks to stop from a command one tick faster than v_ref
    S = dt * (N + 1.0) / 2.0
    if ratio * S == 0.0:
        return V[:0], c[:0]
    dS = np.sign(v[js]) / (2.0 * acc[js])  # dS/dv_js
    m = 0
    w = np.empty(nv)
    for i in range(K):
        ck = _curvature(J[order[i]], z[i], v, w)
        cm = min(ck, 0.0)
        rhs = S * ck + cm * dS * v[js]
        low = 0.0  # the row's least value over the box
        for j in range(nv):
            V[m, j] = A[i, j] + 2.0 * S * w[j]
        V[m, js] += cm * dS
        for j in range(nv):
            low += min(V[m, j] * lo[j], V[m, j] * hi[j])
        if low < rhs:  # the box holds commands that break it: keep
            c[m] = rhs
            m += 1
    return V[:m], c[:m]


@numba.njit(cache=True, nogil=True)
def _curvature(Jk, zk, v, w):
    """`w = -Jdot(v)^T z` (written into w) and `c = w . v` for one taxel (module docstring)."""
    nv = Jk.shape[1]
    P = np.zeros(3)
    for j in range(nv):
        for r in range(3):
            P[r] += v[j] * Jk[r, j]
    Om = np.zeros(3)
    c = 0.0
    for i in range(nv):
        for r in range(3):
            Om[r] += v[i] * Jk[3 + r, i]
            P[r] -= v[i] * Jk[r, i]
        jx, jy, jz = Jk[0, i], Jk[1, i], Jk[2, i]
        ox, oy, oz = Jk[3, i], Jk[4, i], Jk[5, i]
        dx = Om[1] * jz - Om[2] * jy + oy * P[2] - oz * P[1]
        dy = Om[2] * jx - Om[0] * jz + oz * P[0] - ox * P[2]
        dz = Om[0] * jy - Om[1] * jx + ox * P[1] - oy * P[0]
        w[i] = -(dx * zk[0] + dy * zk[1] + dz * zk[2])
        c += w[i] * v[i]
    return c


def curvature(J: np.ndarray, z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, nv) `w_k = d(a_k . v)/dq` and (K,) `c_k = w_k . v` of taxels with Jacobians J (K, 6, nv)
    and normals z (K, 3) at joint velocity v (module docstring)."""
    J, z, v = (np.ascontiguousarray(x, dtype=np.float64) for x in (J, z, v))
    W, c = np.zeros((len(J), J.shape[2])), np.zeros(len(J))
    for k in range(len(J)):
        c[k] = _curvature(J[k], z[k], v, W[k])
    return W, c

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
fall infeasible 2-3x as often). Rows the whole acceleration box already meets are dropped, no-push
rows and viability rows alike (`hard_rows`: they cannot bind, the tick's command lies in the box),
so a DAQP level only sees the rows that matter.

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

SAME = 1e-3
"""A viability row within this relative distance of its taxel's no-push row adds nothing the no-push
row does not already ask, and the near-duplicate pair makes DAQP's active set degenerate: on 300
Panda 8-contact sets, dropping such rows took the sets with a tick where DAQP gave up (`solver_failed`)
from 6 to 0 and the infeasible ones from 21 to 10, with no push in either."""


def check_joints(model: mujoco.MjModel) -> None:
    """The curvature formula needs hinge and slide joints; a ball or free joint is refused."""
    bad = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or str(j) for j in range(model.njnt)
           if int(model.jnt_type[j]) not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))]
    if bad:
        raise ValueError(f"viability: joints {bad} are ball or free joints; the retraction's viability rows "
                         "need hinge and slide joints (model the robot's joints as revolute or prismatic)")


def hard_rows(J: np.ndarray, order: np.ndarray, st: np.ndarray, A: np.ndarray, b: np.ndarray, v_ref: np.ndarray,
              lo: np.ndarray, hi: np.ndarray, acc: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray, int]:
    """The hard rows `R qd >= r` of a tick that can bind: the no-push rows `A qd >= b` and the
    viability rows (module docstring), each kept only where some command in the box [lo, hi]
    breaks it (the others hold for every command the tick may send). Returns R, r and how many
    of them (the first ones) are no-push rows.

    J (K', 6, nv): the taxels' Jacobians; `order` (K,): the pool's taxels, highest priority first,
    as rows of J; st (K, 9): the pool's rows in that order (columns 6:9 the normals when touched);
    A (K, nv), b (K,): their no-push rows (same order); `v_ref` the velocity the tick starts from;
    acc the acceleration limits. One compiled call, no allocation per taxel."""
    return _rows(J, order, st, A, b, v_ref, lo, hi, acc, float(dt))


def braking_horizon(v_ref: np.ndarray, acc: np.ndarray, dt: float) -> float:
    """S: how far (in seconds of motion at the command's speed) the arm travels along the command
    while it brakes in proportion from a command one tick faster than `v_ref` (module docstring);
    `dt` where it is at rest."""
    S, _ = _horizon(np.asarray(v_ref, dtype=np.float64), np.asarray(acc, dtype=np.float64), float(dt))
    return S if S > 0 else float(dt)


@numba.njit(cache=True, nogil=True)
def _horizon(v, acc, dt):
    """(S, the joint that needs longest to stop); S = 0 at rest."""
    ratio, js = 0.0, 0
    for j in range(len(v)):
        x = abs(v[j]) / (acc[j] * dt)  # 0 where acc is infinite: stops within the tick
        if x > ratio:
            ratio, js = x, j
    if ratio == 0.0:
        return 0.0, js
    return dt * (np.ceil(ratio) + 2.0) / 2.0, js  # N + 1 ticks: from a command one tick faster than v_ref


@numba.njit(cache=True, nogil=True)
def _low(row, lo, hi):
    """The least value of `row . qd` over the box."""
    out = 0.0
    for j in range(len(row)):
        out += min(row[j] * lo[j], row[j] * hi[j])
    return out


@numba.njit(cache=True, nogil=True)
def _rows(J, order, st, A, b, v, lo, hi, acc, dt):
    K, nv = A.shape
    R, r = np.empty((2 * K, nv)), np.empty(2 * K)
    m = 0
    for i in range(K):
        if _low(A[i], lo, hi) < b[i]:
            R[m], r[m] = A[i], b[i]
            m += 1
    n_push = m
    S, js = _horizon(v, acc, dt)
    if S == 0.0:  # at rest: the brake is this tick's command, the no-push rows cover it
        return R[:m], r[:m], n_push
    dS = (1.0 if v[js] > 0 else -1.0) / (2.0 * acc[js])  # dS/dv_js
    for i in range(K):
        ck = _curvature(J[order[i]], st[i, 6], st[i, 7], st[i, 8], v, R[m])  # R[m] = w
        cm = min(ck, 0.0)
        for j in range(nv):
            R[m, j] = A[i, j] + 2.0 * S * R[m, j]
        R[m, js] += cm * dS
        r[m] = S * ck + cm * dS * v[js]
        dev = 0.0
        nrm = 0.0
        for j in range(nv):
            dev += (R[m, j] - A[i, j]) ** 2
            nrm += A[i, j] ** 2
        if _low(R[m], lo, hi) < r[m] and dev > SAME * SAME * nrm:  # can bind, and is not its no-push row again
            m += 1
    return R[:m], r[:m], n_push


@numba.njit(cache=True, nogil=True)
def _curvature(Jk, z0, z1, z2, v, w):
    """`w = -Jdot(v)^T z` (written into w) and `c = w . v` for one taxel (module docstring)."""
    nv = Jk.shape[1]
    p0 = p1 = p2 = 0.0  # P_i = sum_{j>i} v_j J_j, from the full sum down
    for j in range(nv):
        p0 += v[j] * Jk[0, j]
        p1 += v[j] * Jk[1, j]
        p2 += v[j] * Jk[2, j]
    o0 = o1 = o2 = 0.0  # Omega_i = sum_{j<=i} v_j omega_j
    c = 0.0
    for i in range(nv):
        jx, jy, jz = Jk[0, i], Jk[1, i], Jk[2, i]
        ox, oy, oz = Jk[3, i], Jk[4, i], Jk[5, i]
        o0 += v[i] * ox
        o1 += v[i] * oy
        o2 += v[i] * oz
        p0 -= v[i] * jx
        p1 -= v[i] * jy
        p2 -= v[i] * jz
        dx = o1 * jz - o2 * jy + oy * p2 - oz * p1
        dy = o2 * jx - o0 * jz + oz * p0 - ox * p2
        dz = o0 * jy - o1 * jx + ox * p1 - oy * p0
        w[i] = -(dx * z0 + dy * z1 + dz * z2)
        c += w[i] * v[i]
    return c


def curvature(J: np.ndarray, z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, nv) `w_k = d(a_k . v)/dq` and (K,) `c_k = w_k . v` of taxels with Jacobians J (K, 6, nv)
    and normals z (K, 3) at joint velocity v (module docstring)."""
    J, z, v = (np.ascontiguousarray(x, dtype=np.float64) for x in (J, z, v))
    W, c = np.zeros((len(J), J.shape[2])), np.zeros(len(J))
    for k in range(len(J)):
        c[k] = _curvature(J[k], z[k, 0], z[k, 1], z[k, 2], v, W[k])
    return W, c

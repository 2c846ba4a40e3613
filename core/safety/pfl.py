"""Power and force limiting (ISO/TS 15066) from the skin: every taxel's effective robot mass along
its normal and the highest approach speed that keeps a transient contact within the body
region's limit; a speed cap for the safety stack.

The ISO/TS 15066 Annex A table (`REGIONS`, with its sources and second-source check) lives with
the body model in `skinsafe.core.sim.body_regions` (the person in a scene reads it too).

- Effective robot mass at taxel i along its outward normal z_i (ISO/TS 15066 A.3.2; Haddadin):
  `m_R = 1 / (z^T J_p M(q)^-1 J_p^T z)`. The row `a_i = J_p,i^T z_i` is one small product per
  skinned body: with the body Jacobian `[J_p; J_r]` (world frame, at the body origin), R the
  body rotation and the taxel's local position p and normal n, `a_i = [n, p x n] . [R^T J_p; R^T J_r]`
  (`[n, p x n]` is the unit force along the normal as a wrench about the body origin, a constant
  of the design). `mujoco.mj_solveM` gives `M^-1 a` for all taxels at once.
- Highest safe approach speed (ISO/TS 15066 eq. A.6):
  `v_max = F_T / sqrt(mu k)`, `mu = (1/m_H + 1/m_R)^-1`, written as `F_T / sqrt(k) * sqrt(1/m_H + 1/m_R)`
  so a taxel that cannot move along its normal (`1/m_R = 0`) needs no division.
- `PFLCap`: each taxel's velocity along its outward normal, `a_i . qdot`, capped at the smallest
  `v_max` over the scene's regions (the most sensitive one), times a margin `factor`. The command
  is scaled as a whole (direction kept, so a planned path stays the path); a non-finite joint
  state, command or mass gives a stop and a counted flag.
"""
from __future__ import annotations

import mujoco
import numba
import numpy as np

from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.sim.body_regions import REGIONS, Region, region

__all__ = ["REGIONS", "Region", "region", "v_max", "NormalRows", "inverse_effective_mass",
           "effective_mass", "taxel_speed_limits", "PFLCap"]


def v_max(reg: Region | str, inv_m_r) -> np.ndarray:
    """Highest approach speed (m/s) for a transient contact within `reg`'s limit, per taxel, from
    the inverse effective robot masses `1/m_R` (1/kg, 0 for a taxel that cannot move)."""
    reg = region(reg) if isinstance(reg, str) else reg
    inv = np.asarray(inv_m_r, float)
    return reg.transient_limit() / np.sqrt(reg.k_N_per_m) * np.sqrt(1.0 / reg.mass_kg + inv)


def normal_wrenches(kin: TaxelKinematics) -> np.ndarray:
    """(N, 6) `[n, p x n]` per taxel in its body frame: a unit force along the outward normal as a
    wrench about the body origin (constant for a design)."""
    n = kin.local_frames[:, :, 2]
    return np.ascontiguousarray(np.hstack([n, np.cross(kin.local_pos, n)]))


class NormalRows:
    """`a_i = J_p,i^T z_i` (N, nv) for all taxels at q: one body Jacobian per skinned body (the
    `TaxelKinematics` groups and data), then one (n_b, 6) x (6, nv) product per body."""

    def __init__(self, kin: TaxelKinematics):
        self.kin = kin
        self.wrench = normal_wrenches(kin)
        nv = kin.model.nv
        self.rows = np.zeros((kin.n, nv))
        self._jac = np.zeros((6, nv))
        self._G = np.zeros((6, nv))

    def __call__(self, q: np.ndarray | None = None) -> np.ndarray:
        """The rows at q (or the data's qpos); the array is reused by the next call."""
        kin = self.kin
        kin.update(q)
        d, m, J, G = kin.data, kin.model, self._jac, self._G
        for bid, sel in kin.groups:
            mujoco.mj_jacBody(m, d, J[:3], J[3:], bid)
            R = d.xmat[bid].reshape(3, 3)
            np.matmul(R.T, J[:3], out=G[:3])
            np.matmul(R.T, J[3:], out=G[3:])
            if isinstance(sel, slice):
                np.matmul(self.wrench[sel], G, out=self.rows[sel])
            else:
                self.rows[sel] = self.wrench[sel] @ G
        return self.rows


def inverse_effective_mass(kin: TaxelKinematics, rows: np.ndarray) -> np.ndarray:
    """`1/m_R = a^T M^-1 a` (N,) per taxel for rows `a` (N, nv) computed at the data's current
    configuration (`NormalRows` leaves it there): the mass matrix is built and factorised once,
    `mj_solveM` solves for all taxels at once."""
    m, d = kin.model, kin.data
    mujoco.mj_crb(m, d)
    mujoco.mj_factorM(m, d)
    x = np.empty_like(rows)
    if len(rows):
        mujoco.mj_solveM(m, d, x, rows)
    return np.einsum("ij,ij->i", rows, x)


def effective_mass(kin: TaxelKinematics, q: np.ndarray | None = None) -> np.ndarray:
    """Effective robot mass (kg) at every taxel along its outward normal at q (inf where the
    robot cannot move the taxel along its normal)."""
    inv = inverse_effective_mass(kin, NormalRows(kin)(q))
    with np.errstate(divide="ignore"):
        return np.where(inv > 0, 1.0 / np.maximum(inv, 0.0), np.inf)


def taxel_speed_limits(kin: TaxelKinematics, regions, q: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Per region name, v_max (m/s) of every taxel at q."""
    inv = inverse_effective_mass(kin, NormalRows(kin)(q))
    return {name: v_max(name, inv) for name in regions}


class PFLCap:
    """The PFL speed cap for the safety stack: `cap(q, qdot) -> qdot` with every taxel's velocity
    along its outward normal at most `factor * v_max` of the most sensitive of `regions`.

    Per tick: one body Jacobian per skinned body gives `G_b` (6, nv) (`NormalRows`), `mj_solveM`
    gives `M^-1 G_b^T`, so each taxel's `1/m_R = w^T (G_b M^-1 G_b^T) w` and normal speed
    `w . (G_b qdot)` with its constant wrench w: a 6x6 quadratic form per taxel in one compiled
    pass, no (N, nv) arrays. After a call: `last_scale` (1 = untouched), `last_taxel` (the taxel
    that bound, -1 none), `vmax` and `vn` (N,: each taxel's cap and normal speed), `flags` (count of non-finite inputs answered with a stop).
    """

    def __init__(self, kin: TaxelKinematics, regions=("hand",), factor: float = 1.0):
        self.kin = kin
        names = (regions,) if isinstance(regions, str) else tuple(regions)
        if not names:
            raise ValueError("PFLCap: give at least one body region (e.g. 'hand')")
        regs = [region(r) for r in names]
        if not (np.isfinite(factor) and 0 < factor <= 1):
            raise ValueError(f"PFLCap: factor is {factor}; give a margin in (0, 1] (1 = the ISO limit)")
        self.regions, self.factor = names, float(factor)
        # v_max = c * sqrt(1/m_H + 1/m_R), per region
        self._c = np.array([factor * r.transient_limit() / np.sqrt(r.k_N_per_m) for r in regs])
        self._inv_mh = np.array([1.0 / r.mass_kg for r in regs])
        self.wrench = normal_wrenches(kin)
        self.bodies = np.unique(kin.body_id)
        self.slot = np.searchsorted(self.bodies, kin.body_id).astype(np.int64)
        nv, nb = kin.model.nv, len(self.bodies)
        self._G = np.zeros((nb, 6, nv))
        self._J = np.zeros((6, nv))
        self._MG = np.zeros((nb * 6, nv))
        self.last_scale, self.last_taxel, self.flags = 1.0, -1, 0
        self.vmax = np.zeros(kin.n)
        self.vn = np.zeros(kin.n)

    def _body_terms(self, q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """H_b = G_b M^-1 G_b^T (nb, 6, 6) and G_b qdot (nb, 6) at q."""
        kin = self.kin
        kin.update(q)
        m, d, G, J = kin.model, kin.data, self._G, self._J
        for k, bid in enumerate(self.bodies):
            mujoco.mj_jacBody(m, d, J[:3], J[3:], int(bid))
            R = d.xmat[bid].reshape(3, 3)
            np.matmul(R.T, J[:3], out=G[k, :3])
            np.matmul(R.T, J[3:], out=G[k, 3:])
        mujoco.mj_crb(m, d)
        mujoco.mj_factorM(m, d)
        G2 = G.reshape(-1, m.nv)
        mujoco.mj_solveM(m, d, self._MG, G2)
        H = np.matmul(G, self._MG.reshape(G.shape).transpose(0, 2, 1))
        return H, G @ v

    def __call__(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        v = np.asarray(v, dtype=float)
        q = np.asarray(q, dtype=float)
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(v))):
            return self._stop(v)
        H, gv = self._body_terms(q, v)
        scale, k = _cap_pass(self.wrench, self.slot, H, gv, self._c, self._inv_mh, self.vmax, self.vn)
        if not np.isfinite(scale):
            return self._stop(v)
        self.last_scale, self.last_taxel = float(scale), int(k)
        return v * scale if k >= 0 else v

    def _stop(self, v: np.ndarray) -> np.ndarray:
        self.flags += 1
        self.last_scale, self.last_taxel = 0.0, -1
        return np.zeros(np.shape(v))


@numba.njit(cache=True, nogil=True)
def _cap_pass(wrench, slot, H, gv, c, inv_mh, vmax, vn):
    """Per taxel: 1/m_R = w^T H w, normal speed w . gv, v_max (min over regions); returns the
    largest scale in [0, 1] keeping every taxel within its v_max and the taxel that binds (-1:
    none); a NaN scale when a mass or speed is not finite."""
    scale, best = 1.0, -1
    for i in range(wrench.shape[0]):
        b = slot[i]
        inv, s = 0.0, 0.0
        for r in range(6):
            hw = 0.0
            for col in range(6):
                hw += H[b, r, col] * wrench[i, col]
            inv += wrench[i, r] * hw
            s += wrench[i, r] * gv[b, r]
        if not (np.isfinite(inv) and np.isfinite(s)):
            return np.nan, -1
        inv = max(inv, 0.0)
        vm = np.inf
        for k in range(c.shape[0]):
            vm = min(vm, c[k] * np.sqrt(inv_mh[k] + inv))
        vmax[i], vn[i] = vm, s
        if s > vm + 1e-12 and vm < scale * s:
            scale, best = vm / s, i
    return scale, best

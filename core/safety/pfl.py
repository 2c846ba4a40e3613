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
import numpy as np

from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.sim.body_regions import REGIONS, Region, region

__all__ = ["REGIONS", "Region", "region", "reduced_mass", "v_max", "NormalRows", "inverse_effective_mass",
           "effective_mass", "taxel_speed_limits", "PFLCap"]


def reduced_mass(m_h, m_r) -> np.ndarray:
    """`mu = (1/m_H + 1/m_R)^-1` (kg); m_R may be inf (a taxel that cannot move along its normal)."""
    return 1.0 / (1.0 / np.asarray(m_h, float) + 1.0 / np.asarray(m_r, float))


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

    After a call: `last_scale` (1 = untouched), `last_taxel` (the taxel that bound, -1 none),
    `flags` (count of non-finite inputs answered with a stop).
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
        self.normal_rows = NormalRows(kin)
        self.last_scale, self.last_taxel, self.flags = 1.0, -1, 0
        self.vmax = np.zeros(kin.n)

    def limits(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows `a` (N, nv) and the cap `factor * v_max` (N,) of the most sensitive region at q."""
        rows = self.normal_rows(q)
        inv = inverse_effective_mass(self.kin, rows)
        vm = self._c[0] * np.sqrt(self._inv_mh[0] + inv)
        for c, ih in zip(self._c[1:], self._inv_mh[1:]):
            np.minimum(vm, c * np.sqrt(ih + inv), out=vm)
        self.vmax = vm
        return rows, vm

    def __call__(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        v = np.asarray(v, dtype=float)
        q = np.asarray(q, dtype=float)
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(v))):
            return self._stop(v)
        rows, vm = self.limits(q)
        vn = rows @ v  # each taxel's velocity along its outward normal (m/s)
        if not (np.all(np.isfinite(vn)) and np.all(np.isfinite(vm))):
            return self._stop(v)
        out = vn > np.maximum(vm, 0.0) + 1e-12
        if not out.any():
            self.last_scale, self.last_taxel = 1.0, -1
            return v
        ratio = np.where(out, np.maximum(vm, 0.0) / np.where(out, vn, 1.0), 1.0)
        k = int(np.argmin(ratio))
        self.last_scale, self.last_taxel = float(ratio[k]), k
        return v * ratio[k]

    def _stop(self, v: np.ndarray) -> np.ndarray:
        self.flags += 1
        self.last_scale, self.last_taxel = 0.0, -1
        return np.zeros(np.shape(v))

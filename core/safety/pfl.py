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
- Pressure (ISO/TS 15066 A.3.3): with the contact area A a taxel stands for (`area`, e.g. its
  cell, `body_regions.contact_areas`), the force a contact may reach is also `p_max A`, so
  `F_T = min(F_T, p_T A)` per taxel.
- Clamping (ISO/TS 15066 5.5.5.4: quasi-static, the body part cannot recoil): a taxel that faces a
  fixed surface (`fixtures`, half-spaces) within `clamp_gap` can trap a body part against it. The
  part then cannot move away (m_H drops out) and is compressed by the robot's kinetic energy,
  `v sqrt(m_R / k)`, plus what the robot covers while the stack reacts and its servo follows,
  `v (stop_s + lag_s)`; within the quasi-static limit `F_Q = min(F_qs, p_qs A)` (compression `F_Q / k`)
  that gives `v_max = (F_Q / k) / (sqrt(m_R / k) + stop_s + lag_s)`.
- `PFLCap`: each taxel's velocity along its outward normal, `a_i . qdot`, capped at the smallest
  `v_max` over the scene's regions (the most sensitive one), times a margin `factor`. The command
  is scaled as a whole (direction kept, so a planned path stays the path); a non-finite joint
  state, command or mass gives a stop and a counted flag. Where the person is known
  (`observe(Person)`, body parts as capsules with their velocities), a taxel is capped only by the
  parts within `reach` in front of it (its normal within 45 degrees of the part: a taxel facing
  elsewhere is not where the part would be met), and by the relative velocity: the taxel's normal speed
  minus the part's along the same normal, `a_i . qdot - n_i . v_part <= v_max`. A region with no
  transient contact allowed (skull, face: `v_max = 0`) is avoided, not frozen at: a taxel may
  approach it at `avoid_gain (d - keep_out)`, d its distance, and must back away inside
  `keep_out`. A taxel touching a part (within `TOUCHING`) gives way: it separates from the part at
  `give_way` m/s, relative (pressing on is a push, not the impact v_max is made for; a part the
  person presses onto the robot is yielded to, not resisted). When any bound is negative (a part closing in faster than allowed, or inside the
  keep-out) scaling cannot meet it: the command is the nearest one that does (a small QP,
  DAQP), i.e. the robot retreats.
- Braking before the contact (`acc`, the joint acceleration limits the stack brakes at): the command
  is scaled as a whole, so braking it in the least time the limits allow, `h = max_j |qdot_j| / acc_j`,
  slows taxel i's normal speed u at `a_i = u / h` (the same for any scale of the command). The taxel
  keeps u for the reaction time `tau = stop_s + lag_s` (the stack's reaction and the servo's lag, how
  late the arm follows its command: the sim's UR5 pan 69 ms) and then brakes, so it covers
  `u tau + u^2 / (2 a_i)` before it is at rest. That may be no more than the distance d to the part plus
  what a lag-free arm meeting the part at v_max covers braking after the contact, `v_max^2 / (2 a_i)`:
  `u <= -a_i tau + sqrt((a_i tau)^2 + v_max^2 + 2 a_i d)` (transient or clamping v_max; d = 0 where the
  person is not observed, so below v_max: only a part seen far enough away allows more). Where the arm's measured normal speed u_m is the faster (its servo lags a
  braking command), it covers `u_m tau` first: `u <= sqrt(v_max^2 + 2 a_i (d - u_m tau))`, 0 where
  even that does not fit. Without it the cap allowed v_max up to the part: a robot whose servo lags
  arrives at v_max and pushes on into the part for its reaction and braking (the collaboration's
  delivery: 0.21 rad of pan in 190 ms after the contact, a hand at 428 N where 280 N is the limit).
"""
from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numba
import numpy as np

from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.sim.body_regions import REGIONS, Region, region

FACING = np.cos(np.pi / 4)  # a part constrains a taxel whose normal points within 45 degrees of it
TOUCHING = 0.0  # m: a taxel this close to a part (inside it: in contact) gives way (a push, not an impact)

__all__ = ["REGIONS", "Region", "region", "v_max", "NormalRows", "inverse_effective_mass",
           "effective_mass", "taxel_speed_limits", "Person", "PFLCap"]


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


@dataclass
class Person:
    """Where the person is, for `PFLCap.observe`: per body part its region name, its core as a
    segment `a`-`b` (world, m; a = b for a ball), its `radius` and its `velocity` (world, m/s)."""

    regions: tuple
    a: np.ndarray  # (P, 3)
    b: np.ndarray  # (P, 3)
    radius: np.ndarray  # (P,)
    velocity: np.ndarray  # (P, 3)


class PFLCap:
    """The PFL speed cap for the safety stack: `cap(q, qdot) -> qdot` with every taxel's velocity
    along its outward normal at most `factor * v_max` of the most sensitive of `regions` (module
    docstring: pressure through `area` (N,) m^2, clamping against `fixtures` [(point, outward
    normal)], the person's parts and velocities through `observe`, braking before the contact at the
    joint acceleration limits `acc` after the reaction `stop_s` and the servo's lag `lag_s`).

    Per tick: one body Jacobian per skinned body gives `G_b` (6, nv) (`NormalRows`), `mj_solveM`
    gives `M^-1 G_b^T`, so each taxel's `1/m_R = w^T (G_b M^-1 G_b^T) w` and normal speed
    `w . (G_b qdot)` with its constant wrench w: a 6x6 quadratic form per taxel in one compiled
    pass, no (N, nv) arrays. After a call: `last_scale` (1 = untouched, 0 = stopped or retreating),
    `last_taxel` (the taxel that bound, -1 none), `last_mode` ("free", "scaled", "retreat", "stop"),
    `vmax` and `vn` (N,: each taxel's cap and normal speed), `bound` (N,: the cap on its normal
    speed, the part's velocity included; inf where no part is near), `clamp` (N,: facing a
    fixture), `flags` (non-finite inputs answered with a stop), `retreats` (ticks that needed
    one) and `failed` (retreats with no command meeting every bound: a stop).
    """

    def __init__(self, kin: TaxelKinematics, regions=("hand",), factor: float = 1.0, area=None, fixtures=(),
                 clamp_gap: float = 0.12, stop_s: float = 0.02, reach: float = 0.3, keep_out: float = 0.1,
                 avoid_gain: float = 2.0, give_way: float = 0.2, acc=None, lag_s: float = 0.0):
        self.kin = kin
        names = (regions,) if isinstance(regions, str) else tuple(regions)
        if not names:
            raise ValueError("PFLCap: give at least one body region (e.g. 'hand')")
        regs = [region(r) for r in names]
        if not (np.isfinite(factor) and 0 < factor <= 1):
            raise ValueError(f"PFLCap: factor is {factor}; give a margin in (0, 1] (1 = the ISO limit)")
        for name, value in (("clamp_gap", clamp_gap), ("stop_s", stop_s), ("reach", reach), ("keep_out", keep_out),
                            ("avoid_gain", avoid_gain), ("give_way", give_way), ("lag_s", lag_s)):
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"PFLCap: {name} is {value}; give a finite number >= 0")
        self.regions, self.factor = names, float(factor)
        # per region: transient / quasi-static force (N) and pressure (N/m^2), 1/m_H, k
        self._reg = np.array([[r.transient_limit(), r.quasi_static_N, 1e4 * r.pressure_limit("transient"),
                               1e4 * r.pressure_limit("quasi_static"), 1.0 / r.mass_kg, r.k_N_per_m] for r in regs])
        area = np.full(kin.n, np.inf) if area is None else np.asarray(area, float)
        if area.shape != (kin.n,) or not np.all(area > 0):
            raise ValueError(f"PFLCap: area has shape {area.shape}; give one positive contact area (m^2) per taxel")
        self.area = np.ascontiguousarray(area)
        fx = np.array([np.r_[np.asarray(o, float), np.asarray(u, float) / np.linalg.norm(u)] for o, u in fixtures])
        self._fixtures = fx.reshape(-1, 6)
        if acc is not None:
            acc = np.asarray(acc, float)
            if acc.shape not in ((), (kin.model.nv,)) or not np.all(np.isfinite(acc) & (acc > 0)):
                raise ValueError(f"PFLCap: acc is {acc}; give the joint acceleration limits the stack brakes at "
                                 "(rad/s^2, finite and > 0, one per joint or one for all), or None")
            acc = np.broadcast_to(acc, (kin.model.nv,)).copy()
        self.acc = acc
        # the options; [6]: 1 with the braking model (`acc`), [7]: 1/h of the command this call, [8]: its reaction
        # time (module docstring)
        self._opts = np.array([clamp_gap, stop_s, reach, keep_out, avoid_gain, give_way, float(acc is not None), 0.0,
                               stop_s + lag_s])
        self.wrench = normal_wrenches(kin)
        self.local_normal = np.ascontiguousarray(kin.local_frames[:, :, 2])
        self.bodies = np.unique(kin.body_id)
        self.slot = np.searchsorted(self.bodies, kin.body_id).astype(np.int64)
        nv, nb = kin.model.nv, len(self.bodies)
        self._G = np.zeros((nb, 6, nv))
        self._J = np.zeros((6, nv))
        self._MG = np.zeros((nb * 6, nv))
        self.last_scale, self.last_taxel, self.last_mode = 1.0, -1, "free"
        self.flags = self.retreats = self.failed = 0
        self.vmax, self.vn, self.bound = np.zeros(kin.n), np.zeros(kin.n), np.zeros(kin.n)
        self.clamp = np.zeros(kin.n, bool)
        self.observe(None)

    def observe(self, person: Person | None) -> None:
        """Where the person is (until the next call); None: unknown (every region everywhere, at
        rest: a region with no transient contact allowed then stops the robot)."""
        if person is None:
            self._parts = np.zeros((0, 11))
            return
        idx = []
        for r in person.regions:
            if r not in self.regions:
                raise ValueError(f"PFLCap.observe: region '{r}' is not one of the cap's {self.regions}")
            idx.append(self.regions.index(r))
        cols = [np.asarray(idx, float)[:, None], np.asarray(person.a, float), np.asarray(person.b, float),
                np.asarray(person.radius, float)[:, None], np.asarray(person.velocity, float)]
        self._parts = np.ascontiguousarray(np.hstack(cols))

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

    def __call__(self, q: np.ndarray, v: np.ndarray, qdot: np.ndarray | None = None) -> np.ndarray:
        """The capped command for the joint state q and the command v; `qdot`, the arm's measured joint
        velocity where known (the braking model: an arm faster than its command brakes from its own speed)."""
        v = np.asarray(v, dtype=float)
        q = np.asarray(q, dtype=float)
        qdot = np.zeros_like(v) if qdot is None else np.asarray(qdot, dtype=float)
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(v)) and np.all(np.isfinite(qdot))
                and np.all(np.isfinite(self._parts))):
            return self._stop(v)
        H, gv = self._body_terms(q, v)
        gm = self._G @ qdot
        if self.acc is not None:  # 1/h: the least time the joint limits allow to brake the command as a whole
            moving = v != 0
            self._opts[7] = np.min(self.acc[moving] / np.abs(v[moving])) if moving.any() else np.inf
        d = self.kin.data
        Rb = np.ascontiguousarray(d.xmat[self.bodies].reshape(-1, 3, 3))
        Xb = np.ascontiguousarray(d.xpos[self.bodies])
        ok = _bounds(self.wrench, self.slot, H, gv, gm, Rb, Xb, self.kin.local_pos, self.local_normal, self.area,
                     self._reg, self.factor, self._fixtures, self._opts, self._parts, self.vmax, self.vn, self.bound,
                     self.clamp)
        if not ok:
            return self._stop(v)
        near = np.isfinite(self.bound)
        if np.all(self.bound[near] >= 0):  # scaling meets every bound (a stop does): keep the path
            over = near & (self.vn > self.bound + 1e-12)
            if not over.any():
                self.last_scale, self.last_taxel, self.last_mode = 1.0, -1, "free"
                return v
            ratio = np.where(over, self.bound / np.where(over, self.vn, 1.0), np.inf)
            k = int(np.argmin(ratio))
            self.last_scale, self.last_taxel, self.last_mode = float(ratio[k]), k, "scaled"
            return v * ratio[k]
        return self._retreat(v, np.flatnonzero(near))

    def _retreat(self, v: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """The command nearest to v meeting every bound (some are negative: the robot must move
        the taxels away); a stop (and `failed`) where none does."""
        from skinsafe.core.safety import qp  # DAQP only where a retreat is needed: the add-on's map never loads it

        self.retreats += 1
        A = np.einsum("ij,ijk->ik", self.wrench[rows], self._G[self.slot[rows]])
        n = len(v)
        x, ok, _ = qp.solve(np.eye(n), -v, np.ascontiguousarray(A), np.full(len(rows), -qp.BIG),
                            np.ascontiguousarray(self.bound[rows]))
        if not ok:
            self.failed += 1
            self.last_scale, self.last_taxel, self.last_mode = 0.0, -1, "stop"
            return np.zeros(n)
        k = rows[int(np.argmin(self.bound[rows]))]
        self.last_scale, self.last_taxel, self.last_mode = 0.0, int(k), "retreat"
        return x

    def _stop(self, v: np.ndarray) -> np.ndarray:
        self.flags += 1
        self.last_scale, self.last_taxel, self.last_mode = 0.0, -1, "stop"
        return np.zeros(np.shape(v))


@numba.njit(cache=True, nogil=True)
def _limit(reg, r, factor, inv, area, clamp, dist, opts, u, um):
    """v_max of region row `reg[r]` for a taxel whose command moves it along its normal at u and the arm at um
    (module docstring): clamping or transient (with the braking model, at distance `dist`, 0 where unknown), or
    avoidance."""
    ft, fq, pt, pq, inv_mh, k = reg[r]
    if clamp:
        if inv <= 0.0:
            return 0.0
        vm = factor * (min(fq, pq * area) / k) / (1.0 / np.sqrt(inv * k) + opts[8])
    elif ft > 0.0:
        vm = factor * min(ft, pt * area) / np.sqrt(k) * np.sqrt(inv_mh + inv)
    elif np.isfinite(dist):
        return opts[4] * (dist - opts[3])
    else:
        return 0.0
    if opts[6] == 0.0 or u <= 0.0:
        return vm
    a, d, tau = u * opts[7], max(dist, 0.0) if np.isfinite(dist) else 0.0, opts[8]
    lim = -a * tau + np.sqrt((a * tau) ** 2 + vm * vm + 2.0 * a * d)
    if um > lim:  # the arm, faster than its command (its servo lags a braking one), covers tau um first
        lim = np.sqrt(max(vm * vm + 2.0 * a * (d - tau * um), 0.0))
    return lim


@numba.njit(cache=True, nogil=True)
def _bounds(wrench, slot, H, gv, gm, Rb, Xb, lpos, lnrm, area, reg, factor, fixtures, opts, parts, vmax, vn, bound,
            clamp):
    """Per taxel: 1/m_R = w^T H w, normal speed w . gv, world pose, whether it faces a fixture,
    v_max (min over the regions or the near parts) and the bound on its normal speed (v_max plus
    the near parts' velocity along its normal; inf where no part is near). False when a mass or
    speed is not finite. Scalar arithmetic only (no temporaries per taxel)."""
    p, n = np.empty(3), np.empty(3)
    for i in range(wrench.shape[0]):
        b = slot[i]
        inv, s, sm = 0.0, 0.0, 0.0
        for r in range(6):
            hw = 0.0
            for col in range(6):
                hw += H[b, r, col] * wrench[i, col]
            inv += wrench[i, r] * hw
            s += wrench[i, r] * gv[b, r]
            sm += wrench[i, r] * gm[b, r]
        if not (np.isfinite(inv) and np.isfinite(s) and np.isfinite(sm)):
            return False
        inv = max(inv, 0.0)
        vn[i] = s
        if parts.shape[0] == 0 and fixtures.shape[0] == 0:  # the plain cap: the regions everywhere
            vm = np.inf
            for r in range(reg.shape[0]):
                vm = min(vm, _limit(reg, r, factor, inv, area[i], False, np.inf, opts, s, sm))
            vmax[i], bound[i], clamp[i] = vm, vm, False
            continue
        for r in range(3):
            p[r] = Xb[b, r] + Rb[b, r, 0] * lpos[i, 0] + Rb[b, r, 1] * lpos[i, 1] + Rb[b, r, 2] * lpos[i, 2]
            n[r] = Rb[b, r, 0] * lnrm[i, 0] + Rb[b, r, 1] * lnrm[i, 1] + Rb[b, r, 2] * lnrm[i, 2]
        c = False
        for f in range(fixtures.shape[0]):
            h, nu = 0.0, 0.0
            for r in range(3):
                h += (p[r] - fixtures[f, r]) * fixtures[f, 3 + r]
                nu += n[r] * fixtures[f, 3 + r]
            if nu < -0.5 and -1e-9 <= h <= opts[0]:
                c = True
        clamp[i] = c
        vm, bd = np.inf, np.inf
        if parts.shape[0] == 0:
            for r in range(reg.shape[0]):
                vm = min(vm, _limit(reg, r, factor, inv, area[i], c, np.inf, opts, s, sm))
            bd = vm
        for k in range(parts.shape[0]):
            L, u = 0.0, 0.0
            for r in range(3):
                ab = parts[k, 4 + r] - parts[k, 1 + r]
                L += ab * ab
                u += (p[r] - parts[k, 1 + r]) * ab
            u = 0.0 if L <= 0.0 else min(max(u / L, 0.0), 1.0)
            d2, front, vpn = 0.0, 0.0, 0.0
            for r in range(3):
                cp = parts[k, 1 + r] + u * (parts[k, 4 + r] - parts[k, 1 + r])
                d2 += (p[r] - cp) ** 2
                front += (cp - p[r]) * n[r]
                vpn += n[r] * parts[k, 8 + r]
            dist = np.sqrt(d2) - parts[k, 7]
            if dist > opts[2] or front < FACING * np.sqrt(d2):
                continue  # out of reach, or not in front of the taxel (it cannot be where the part is met)
            lim = -opts[5] if dist <= TOUCHING else _limit(reg, int(parts[k, 0]), factor, inv, area[i], c, dist, opts, s, sm)
            vm = min(vm, lim)
            bd = min(bd, lim + vpn)
        vmax[i], bound[i] = vm, bd
    return True

"""Skin readout: the normal force on every taxel, `(N,)` in newtons, from MuJoCo's contacts.

`SkinReadout` does it in one vectorised pass: each contact's normal force (from `efc_force`)
is spread over the enabled taxels of the touched body that lie within a footprint radius R of
the contact point and face it, with weights `1 - d/R` normalised so the taxels' sum equals the
contact's normal force. Candidates come from a precomputed voxel grid per body (body
coordinates, voxel side R). The per-step work runs in one compiled (numba) pass over the
contacts and their candidate taxels: a few microseconds, no Python per contact or per taxel.
A contact with no taxel within R is on bare robot surface and is not sensed (`missed`).

`TouchReadout` reads the per-taxel MuJoCo `touch` sensors the exporter adds with
`SceneOptions(touch_sensors=True)`: exact cells, but MuJoCo loops over every contact for every
sensor, so it is the accuracy reference, not the fast path.
"""
from __future__ import annotations

import mujoco
import numba
import numpy as np
from scipy.spatial import cKDTree

from skinsafe.core.robot.kinematics import body_ids
from skinsafe.core.sim.scene import cell_points
from skinsafe.core.skin.model import DesignError, SkinDesign

BODY_GAP = 1.0e3  # m between bodies when spacing is estimated over all bodies at once


def default_footprint(design: SkinDesign) -> float:
    """The median module pitch of the taxels (or their median nearest-neighbour spacing)."""
    t = design.taxels
    if not len(t):
        return 0.01
    pitch = {m.id: m.pitch for m in design.modules}
    known = [pitch[int(k)] for k in t.module if int(k) in pitch]
    if known:
        return float(np.median(known))
    pts = np.concatenate([t.positions, BODY_GAP * t.body[:, None]], axis=1)
    d, _ = cKDTree(pts).query(pts, k=2)
    return float(np.median(d[:, 1]))


class SkinReadout:
    """Vectorised contact-to-taxel readout with a taxel footprint model.

    After `mj_step`/`mj_forward`, `read(data)` returns a new `(N,)` array of normal forces [N];
    `update(data)` writes them into the readout's own array `forces` and returns it (valid until
    the next update: a control loop's way, with no O(N) allocation or zeroing per step, only the
    taxels lit the step before are cleared).
    `last_missed` counts the contacts of the last read that touched a skinned body but no taxel.
    `kernel`: "linear" spreads a contact over its footprint (weights `1 - d/R`); "nearest" gives
    it all to the nearest facing taxel within R (the cell model of MuJoCo's touch sensors).
    """

    def __init__(self, model: mujoco.MjModel, design: SkinDesign, footprint_radius: float | None = None,
                 kernel: str = "linear"):
        if kernel not in ("linear", "nearest"):
            raise ValueError(f"kernel is '{kernel}'; use 'linear' or 'nearest'")
        self.kernel = kernel
        t = design.taxels
        self.model = model
        self.n = len(t)
        self.radius = float(footprint_radius) if footprint_radius is not None else default_footprint(design)
        if not self.radius > 0:
            raise ValueError(f"footprint_radius is {footprint_radius}; give a positive radius in m")
        self.body_ids = body_ids(model, design)
        # geom -> index into design.bodies, -1 where the geom's body carries no skin
        lut = -np.ones(model.nbody, dtype=np.int64)
        lut[self.body_ids] = np.arange(len(self.body_ids))
        self.geom_skin = lut[model.geom_bodyid]
        g = self.grid = VoxelGrid(t.positions, t.body, t.enabled, len(design.bodies), self.radius)
        # per voxel row: candidate positions, normals and taxel index packed (rows, K, 7); the padding
        # taxel n is far away, so its weight is always 0
        pad = np.vstack([np.hstack([t.positions, t.normals, np.arange(self.n)[:, None]]), [[1e9, 1e9, 1e9, 0, 0, 0, self.n]]])
        self.packed = pad[g.table]
        self.inv_r = 1.0 / self.radius
        rows = _contact_rows(model)
        self.rows = None if rows is None else np.arange(rows)
        self.pyramidal = model.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL
        self.n_rows = -1 if rows is None else rows
        # everything else the compiled pass needs, in one int and one float array (each argument of a
        # compiled call costs ~70 ns to check and unpack; the pass itself takes ~0.1 us)
        body_grid = np.concatenate([self.body_ids[:, None], g.last, g.stride, g.offset[:, None]], axis=1)
        self._ints = np.concatenate([[model.ngeom, len(self.body_ids)], self.geom_skin, body_grid.ravel(), g.row]
                                    ).astype(np.int64)
        self._floats = np.concatenate([[1.0 / g.h, self.inv_r, kernel == "nearest", self.pyramidal, self.n_rows],
                                       g.origin.ravel()])
        # the forces, then how many taxels were written since the last clear and which (as floats: one
        # array for the compiled pass)
        self._state = np.zeros(2 * self.n + 1)
        self.forces = self._state[:self.n]
        self._data = self._xpos = self._xmat = None
        self._missed = 0

    @property
    def last_missed(self) -> int:
        """Contacts of the last read with normal force that no taxel sensed (bare robot surface)."""
        return self._missed

    def contact_forces(self, data: mujoco.MjData, index: np.ndarray | None = None) -> np.ndarray:
        """Normal force of the contacts `index` (default all) from `efc_force` (0 where inactive)."""
        con = data.contact
        adr = con.efc_address[: data.ncon] if index is None else con.efc_address[index]
        if data.nefc == 0:
            return np.zeros(len(adr))
        if self.rows is not None:  # every contact has the same number of rows (same condim and cone)
            return data.efc_force[adr[:, None] + self.rows].sum(axis=1) * (adr >= 0)
        dim = con.dim[: data.ncon] if index is None else con.dim[index]
        active = adr >= 0
        if self.model.opt.cone != mujoco.mjtCone.mjCONE_PYRAMIDAL:
            return np.where(active, data.efc_force[np.maximum(adr, 0)], 0.0)
        # pyramidal cone: the normal force is the sum of the 2(dim-1) pyramid edge forces (1 row if dim 1)
        rows = np.where(dim > 1, 2 * (dim - 1), 1)
        k = np.arange(int(rows.max()) if len(rows) else 1)
        take = active[:, None] & (k < rows[:, None])
        return np.where(take, data.efc_force[np.where(take, adr[:, None] + k, 0)], 0.0).sum(axis=1)

    def read(self, data: mujoco.MjData, warm: bool = False) -> np.ndarray:
        """The taxels' normal forces as a new (N,) array (`warm`: see `update`)."""
        return self.update(data, warm).copy()

    def update(self, data: mujoco.MjData, warm: bool = False) -> np.ndarray:
        """The taxels' normal forces in `self.forces` (overwritten by the next update); `warm=True` runs the
        compiled pass even without contacts, so numba compiles it now (seconds) rather than at a real-time
        loop's first contact."""
        if data is not self._data:  # body poses live in MjData's fixed buffer: one view per MjData
            self._data, self._xpos, self._xmat = data, data.xpos, data.xmat
        if data.ncon == 0 and self._state[self.n] == 0 and not warm:
            self._missed = 0
            return self.forces
        con = data.contact
        self._missed = _readout(self._state, con.geom, con.pos, con.frame, con.efc_address, data.efc_force,
                                self._xpos, self._xmat, self._ints, self._floats, self.packed)
        return self.forces


@numba.njit(cache=True, nogil=True)
def _readout(state, geom, pos, frame, efc_address, efc_force, xpos, xmat, ints, floats, packed):
    """Every contact on a skinned body -> its facing taxels within the footprint (see SkinReadout).
    `state`: the forces (n), then the count and indices of the taxels written since the last
    clear (n + 1; count -1: all may be). Clears those, adds the forces, lists the taxels it writes
    and returns the number of missed contacts.

    ints: n_geoms, n_bodies, then per geom its skinned body (-1: none), per skinned body its MuJoCo
    id, last voxel (3), voxel strides (3) and first voxel, then per voxel its row of `packed`.
    floats: 1 / voxel side, 1 / footprint radius, nearest kernel, pyramidal cone, efc rows per
    contact (-1: they differ; a contact's rows then run to the next contact's, contacts being
    MuJoCo's last constraints), then per skinned body its grid origin (3)."""
    n = (state.shape[0] - 1) // 2
    out, lit = state[:n], state[n:]
    if lit[0] < 0:
        out[:] = 0.0
    for i in range(int(lit[0])):
        out[int(lit[1 + i])] = 0.0
    lit[0] = 0
    inv_h, inv_r, nearest, pyramidal, n_rows = floats[0], floats[1], floats[2] > 0, floats[3] > 0, int(floats[4])
    g0 = 2  # per geom
    b0 = g0 + ints[0]  # per skinned body, 8 each
    v0 = b0 + 8 * ints[1]  # per voxel
    missed = 0
    width = packed.shape[1]
    for c in range(geom.shape[0]):
        adr = efc_address[c]
        if adr < 0:
            continue
        if not pyramidal:
            f = efc_force[adr]
        else:  # pyramidal cone: the normal force is the sum of the pyramid edge forces
            rows = n_rows
            if rows < 0:
                rows = efc_force.shape[0] - adr
                for c2 in range(c + 1, geom.shape[0]):
                    if efc_address[c2] >= 0:
                        rows = efc_address[c2] - adr
                        break
            f = 0.0
            for k in range(rows):
                f += efc_force[adr + k]
        if f <= 0.0:
            continue
        for side in range(2):
            skin = ints[g0 + geom[c, side]]
            if skin < 0:
                continue
            bg = b0 + 8 * skin
            b = ints[bg]
            sign = 1.0 if side == 0 else -1.0  # the contact normal points from geom 0 to geom 1
            # contact point and normal in body coordinates: R^T (p - x), R^T n
            p0, p1, p2 = pos[c, 0] - xpos[b, 0], pos[c, 1] - xpos[b, 1], pos[c, 2] - xpos[b, 2]
            lp0 = xmat[b, 0] * p0 + xmat[b, 3] * p1 + xmat[b, 6] * p2
            lp1 = xmat[b, 1] * p0 + xmat[b, 4] * p1 + xmat[b, 7] * p2
            lp2 = xmat[b, 2] * p0 + xmat[b, 5] * p1 + xmat[b, 8] * p2
            ln0 = xmat[b, 0] * frame[c, 0] + xmat[b, 3] * frame[c, 1] + xmat[b, 6] * frame[c, 2]
            ln1 = xmat[b, 1] * frame[c, 0] + xmat[b, 4] * frame[c, 1] + xmat[b, 7] * frame[c, 2]
            ln2 = xmat[b, 2] * frame[c, 0] + xmat[b, 5] * frame[c, 1] + xmat[b, 8] * frame[c, 2]
            flat = ints[bg + 7]
            for j, x in enumerate((lp0, lp1, lp2)):
                v = min(max(int((x - floats[5 + 3 * skin + j]) * inv_h), 0), ints[bg + 1 + j])
                flat += v * ints[bg + 4 + j]
            row = ints[v0 + flat]
            # two passes over the row's candidates: the weights' total (and the best), then the shares
            total, best, best_k = 0.0, 0.0, -1
            for k in range(width):
                wk = _weight(packed, row, k, lp0, lp1, lp2, ln0 * sign, ln1 * sign, ln2 * sign, inv_r)
                total += wk
                if wk > best:
                    best, best_k = wk, k
            if total <= 0.0:
                missed += 1
                continue
            for k in range(width):
                wk = f if nearest and k == best_k else (
                    0.0 if nearest else _weight(packed, row, k, lp0, lp1, lp2, ln0 * sign, ln1 * sign, ln2 * sign, inv_r)
                    * (f / total))
                if wk <= 0.0:
                    continue
                t = int(packed[row, k, 6])
                if out[t] == 0.0:  # first force on this taxel since the last clear: list it
                    if 0 <= lit[0] < n:
                        lit[1 + int(lit[0])] = t
                        lit[0] += 1
                    else:
                        lit[0] = -1
                out[t] += wk
    return missed


@numba.njit(cache=True, nogil=True, inline="always")
def _weight(packed, row, k, x, y, z, nx, ny, nz, inv_r):
    """Footprint weight 1 - d/R of a packed candidate taxel for a contact at (x, y, z) whose normal
    (nx, ny, nz) points into the skin (0 beyond R or where the taxel faces away)."""
    d2 = ((packed[row, k, 0] - x) ** 2 + (packed[row, k, 1] - y) ** 2 + (packed[row, k, 2] - z) ** 2) * inv_r * inv_r
    if d2 >= 1.0 or packed[row, k, 3] * nx + packed[row, k, 4] * ny + packed[row, k, 5] * nz <= 0.0:
        return 0.0
    return 1.0 - np.sqrt(d2)


def _contact_rows(model: mujoco.MjModel) -> int | None:
    """efc rows per contact when every possible contact has the same count, else None."""
    dims = set(model.geom_condim.tolist()) | set(model.pair_dim.tolist())
    if len(dims) != 1:
        return None
    dim = dims.pop()
    if model.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL:
        return 2 * (dim - 1) if dim > 1 else 1
    return 1


class VoxelGrid:
    """Per-body voxel grids (side h = footprint radius) in body coordinates; each voxel lists the
    enabled taxels within `radius` of any of its points, padded with the index n to a fixed width."""

    def __init__(self, positions: np.ndarray, body: np.ndarray, enabled: np.ndarray, n_bodies: int, radius: float):
        n = len(positions)
        self.h = radius
        self.origin = np.zeros((n_bodies, 3))
        self.dims = np.ones((n_bodies, 3), dtype=np.int64)
        self.offset = np.zeros(n_bodies, dtype=np.int64)
        voxels, members = [], []
        total = 0
        for b in range(n_bodies):
            idx = np.flatnonzero((body == b) & enabled)
            self.offset[b] = total
            if not len(idx):
                total += 1
                continue
            p = positions[idx]
            # a border of voxels more than `radius` from every taxel: clipped lookups land there
            lo = p.min(axis=0) - 2.01 * radius
            dims = np.floor((p.max(axis=0) + 2.01 * radius - lo) / radius).astype(np.int64) + 1
            self.origin[b], self.dims[b] = lo, dims
            # voxels a taxel can reach: the index range of its radius box, kept where the box distance <= radius
            span = np.arange(-1, 2)
            rel = (p - lo) / radius
            base = np.floor(rel).astype(np.int64)
            off = np.stack(np.meshgrid(span, span, span, indexing="ij"), axis=-1).reshape(-1, 3)
            v = base[:, None, :] + off[None]  # (m, 27, 3)
            gap = np.maximum(np.maximum(v - rel[:, None, :], rel[:, None, :] - (v + 1)), 0.0)
            ok = ((gap ** 2).sum(axis=2) <= 1.0 + 1e-9) & (v >= 0).all(axis=2) & (v < dims).all(axis=2)
            flat = total + (v[..., 0] * dims[1] + v[..., 1]) * dims[2] + v[..., 2]
            voxels.append(flat[ok])
            members.append(np.broadcast_to(idx[:, None], ok.shape)[ok])
            total += int(np.prod(dims))
        vox = np.concatenate(voxels) if voxels else np.zeros(0, np.int64)
        mem = np.concatenate(members) if members else np.zeros(0, np.int64)
        order = np.argsort(vox, kind="stable")
        vox, mem = vox[order], mem[order]
        uniq, start, count = np.unique(vox, return_index=True, return_counts=True)
        width = int(count.max()) if len(count) else 1
        # row 0 is empty; voxel -> row through a dense int32 map
        self.table = np.full((len(uniq) + 1, width), n, dtype=np.int64)
        rank = np.arange(len(vox)) - np.repeat(start, count)
        self.table[np.repeat(np.arange(1, len(uniq) + 1), count), rank] = mem
        self.row = np.zeros(total, dtype=np.int32)
        self.row[uniq] = np.arange(1, len(uniq) + 1)

        self.stride = np.stack([self.dims[:, 1] * self.dims[:, 2], self.dims[:, 2], np.ones(n_bodies, np.int64)], 1)
        self.last = self.dims - 1


class TouchReadout:
    """Reference readout: one MuJoCo `touch` sensor per taxel (`touch_<id>` on site `taxel_<id>`)."""

    def __init__(self, model: mujoco.MjModel, design: SkinDesign):
        t = design.taxels
        adr = np.empty(len(t), dtype=np.int64)
        for i, tid in enumerate(t.ids):
            sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, f"touch_{int(tid)}")
            if sid < 0:
                raise DesignError(f"model: touch sensor 'touch_{int(tid)}' of taxel {int(tid)} is missing; "
                                  "export with SceneOptions(touch_sensors=True)")
            adr[i] = model.sensor_adr[sid]
        self.adr = adr
        self.enabled = t.enabled.copy()

    def read(self, data: mujoco.MjData) -> np.ndarray:
        return np.where(self.enabled, data.sensordata[self.adr], 0.0)


class TactileReadout:
    """Reference readout: MuJoCo's native `tactile` sensors (`SceneOptions(tactile_sensors=True)`),
    channel 0 (a pressure from each vertex's penetration depth, not newtons) summed per taxel over
    the vertices in its cell (`per_taxel` as `SceneOptions.tactile_points`)."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, design: SkinDesign, per_taxel: int = 1):
        t = design.taxels
        self.n = len(t)
        pts, owner = cell_points(design, per_taxel)
        self.adr, self.taxel = [], []
        mujoco.mj_kinematics(model, data)
        for bi, body in enumerate(design.bodies):
            sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, f"tactile_{body}")
            if sid < 0:
                continue
            g, mesh = model.sensor_refid[sid], model.sensor_objid[sid]
            nv = model.mesh_vertnum[mesh]
            vert = model.mesh_vert[model.mesh_vertadr[mesh]:model.mesh_vertadr[mesh] + nv]
            b = model.geom_bodyid[g]
            # mesh vertices -> body frame: geom pose relative to its body
            R = data.xmat[b].reshape(3, 3).T @ data.geom_xmat[g].reshape(3, 3)
            x = data.xmat[b].reshape(3, 3).T @ (data.geom_xpos[g] - data.xpos[b])
            on = np.flatnonzero(t.body[owner] == bi)
            _, k = cKDTree(pts[on]).query(vert @ R.T + x)
            self.adr.append(model.sensor_adr[sid] + np.arange(nv))
            self.taxel.append(owner[on[k]])
        self.adr = np.concatenate(self.adr) if self.adr else np.zeros(0, np.int64)
        self.taxel = np.concatenate(self.taxel) if self.taxel else np.zeros(0, np.int64)

    def read(self, data: mujoco.MjData) -> np.ndarray:
        return np.bincount(self.taxel, weights=data.sensordata[self.adr], minlength=self.n)

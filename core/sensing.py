"""Skin readout: the normal force on every taxel, `(N,)` in newtons, from MuJoCo's contacts.

`SkinReadout` does it in one vectorised pass: each contact's normal force (from `efc_force`)
is spread over the enabled taxels of the touched body that lie within a footprint radius R of
the contact point and face it, with weights `1 - d/R` normalised so the taxels' sum equals the
contact's normal force. Candidates come from a precomputed voxel grid per body (body
coordinates, voxel side R): a few array lookups per step, no per-contact Python loop.
A contact with no taxel within R is on bare robot surface and is not sensed (`missed`).

`TouchReadout` reads the per-taxel MuJoCo `touch` sensors the exporter adds with
`ExportOptions(touch_sensors=True)`: exact cells, but MuJoCo loops over every contact for every
sensor, so it is the accuracy reference, not the fast path.
"""
from __future__ import annotations

import mujoco
import numpy as np
from scipy.spatial import cKDTree

from .skin import DesignError, SkinDesign

BODY_GAP = 1.0e3  # m between bodies when spacing is estimated over all bodies at once


def _body_ids(model: mujoco.MjModel, design: SkinDesign) -> np.ndarray:
    ids = []
    for name in design.bodies:
        bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        if bid < 0:
            raise DesignError(f"design: body '{name}' does not exist in the MuJoCo model; "
                              "export the scene from this design (skinsafe export) or fix the body name")
        ids.append(bid)
    return np.asarray(ids, dtype=np.int64)


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

    After `mj_step`/`mj_forward`, `read(data)` returns a new `(N,)` array of normal forces [N].
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
        self.body_ids = _body_ids(model, design)
        # geom -> index into design.bodies, -1 where the geom's body carries no skin
        lut = -np.ones(model.nbody, dtype=np.int64)
        lut[self.body_ids] = np.arange(len(self.body_ids))
        self.geom_skin = lut[model.geom_bodyid]
        self.grid = VoxelGrid(t.positions, t.body, t.enabled, len(design.bodies), self.radius)
        # per voxel row: candidate positions and normals packed (rows, K, 6); the padding taxel n is
        # far away, so its weight is always 0
        pad = np.vstack([np.hstack([t.positions, t.normals]), [[1e9, 1e9, 1e9, 0, 0, 0]]])
        self.packed = pad[self.grid.table]
        self.inv_r = 1.0 / self.radius
        rows = _contact_rows(model)
        self.rows = None if rows is None else np.arange(rows)
        self._force = self._total = np.zeros(0)

    @property
    def last_missed(self) -> int:
        """Contacts of the last read with normal force that no taxel sensed (bare robot surface)."""
        return int(np.count_nonzero((self._total <= 0) & (self._force > 0)))

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

    def read(self, data: mujoco.MjData) -> np.ndarray:
        ncon = data.ncon
        if ncon == 0:
            self._force = self._total = np.zeros(0)
            return np.zeros(self.n)
        con = data.contact
        sides = self.geom_skin[con.geom[:ncon]]  # (ncon, 2) skinned-body index or -1
        ci, side = np.nonzero(sides >= 0)
        if not len(ci):
            self._force = self._total = np.zeros(0)
            return np.zeros(self.n)
        force = self.contact_forces(data, ci)
        skin = sides[ci, side]
        bid = self.body_ids[skin]
        # contact point and normal in body coordinates: R^T (p - x), R^T n
        pn = np.matmul(np.stack((con.pos[ci] - data.xpos[bid], con.frame[ci, :3]), axis=1),
                       data.xmat[bid].reshape(-1, 3, 3))
        row = self.grid.rows(pn[:, 0], skin)
        cand = self.packed[row]  # (k, K, 6)
        d = np.linalg.norm(cand[..., :3] - pn[:, None, 0], axis=2)
        # the contact normal points from geom 0 to geom 1: out of the robot when the robot is geom 0
        facing = np.einsum("kmi,ki->km", cand[..., 3:], pn[:, 1]) * (0.5 - side)[:, None] > 0
        w = np.maximum(1.0 - d * self.inv_r, 0.0) * facing
        if self.kernel == "nearest":
            w = np.where(np.arange(w.shape[1]) == w.argmax(axis=1)[:, None], w, 0.0)
        total = w.sum(axis=1)
        self._force, self._total = force, total
        share = w * (np.maximum(force, 0.0) / np.where(total > 0, total, 1.0))[:, None]
        return np.bincount(self.grid.table[row].ravel(), share.ravel(), self.n + 1)[: self.n]


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

    def rows(self, local: np.ndarray, body: np.ndarray) -> np.ndarray:
        """(k,) table rows of the voxels holding each point (body coordinates); 0 = no taxel near."""
        v = np.clip(((local - self.origin[body]) * (1.0 / self.h)).astype(np.int64), 0, self.last[body])
        return self.row[(v * self.stride[body]).sum(axis=1) + self.offset[body]]

    def candidates(self, local: np.ndarray, body: np.ndarray) -> np.ndarray:
        """(k, K) taxels that may lie within the radius of each point (body coordinates), n = none."""
        return self.table[self.rows(local, body)]


class TouchReadout:
    """Reference readout: one MuJoCo `touch` sensor per taxel (`touch_<id>` on site `taxel_<id>`)."""

    def __init__(self, model: mujoco.MjModel, design: SkinDesign):
        t = design.taxels
        adr = np.empty(len(t), dtype=np.int64)
        for i, tid in enumerate(t.ids):
            sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, f"touch_{int(tid)}")
            if sid < 0:
                raise DesignError(f"model: touch sensor 'touch_{int(tid)}' of taxel {int(tid)} is missing; "
                                  "export with ExportOptions(touch_sensors=True)")
            adr[i] = model.sensor_adr[sid]
        self.adr = adr
        self.enabled = t.enabled.copy()

    def read(self, data: mujoco.MjData) -> np.ndarray:
        return np.where(self.enabled, data.sensordata[self.adr], 0.0)

"""Taxel world poses and Jacobians for all taxels at once.

One MuJoCo body Jacobian per skinned body (`mj_jacBody`), then every taxel on that body gets
`J_p = J_p,body - [r]_x J_r` (r its offset from the body origin, world frame) and `J_r` as is:
one compiled pass over all taxels that writes positions, frames and Jacobians once each.
"""
from __future__ import annotations

import mujoco
import numba
import numpy as np

from skinsafe.core.skin.model import DesignError, SkinDesign


def body_ids(model: mujoco.MjModel, design: SkinDesign) -> np.ndarray:
    """MuJoCo body ids of `design.bodies`; an unknown body is a DesignError naming it."""
    ids = []
    for name in design.bodies:
        bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        if bid < 0:
            raise DesignError(f"design: body '{name}' does not exist in the MuJoCo model; use a body of the robot "
                              "the skin was designed for (or export the scene from this design: skinsafe export)")
        ids.append(bid)
    return np.asarray(ids, dtype=np.int64)


class TaxelKinematics:
    """Poses and Jacobians `(N, 6, nv)` (rows: linear velocity of the taxel point, angular
    velocity; world frame) of a design's taxels on a MuJoCo model."""

    def __init__(self, model: mujoco.MjModel, design: SkinDesign, data: mujoco.MjData | None = None):
        self.model = model
        self.data = data if data is not None else mujoco.MjData(model)
        t = design.taxels
        self.n = n = len(t)
        self.body_id = body_ids(model, design).astype(np.int32)[t.body] if n else np.zeros(0, np.int32)
        self.local_pos = np.ascontiguousarray(t.positions)
        self.local_frames = np.ascontiguousarray(t.frames)
        self._lh = np.hstack([np.ones((n, 1)), t.positions])  # homogeneous local positions (N,4)
        self._ft = np.ascontiguousarray(t.frames.transpose(0, 2, 1)).reshape(3 * n, 3)  # local axes as rows
        # Taxel groups by body: contiguous slices when the design keeps bodies together.
        self.groups = []
        for bid in np.unique(self.body_id):
            idx = np.flatnonzero(self.body_id == bid)
            contiguous = idx[-1] - idx[0] + 1 == len(idx)
            self.groups.append((int(bid), slice(idx[0], idx[-1] + 1) if contiguous else idx))
        nv = model.nv
        self.positions = np.zeros((n, 3))
        self._frames_t = np.zeros((n, 3, 3))
        self.frames = self._frames_t.transpose(0, 2, 1)  # (N,3,3) view: columns x, y, z in world
        self.jac = np.zeros((n, 6, nv))
        # for jacobians_of: the skinned bodies and each taxel's slot among them
        self._bodies = np.unique(self.body_id)
        self._slot = np.searchsorted(self._bodies, self.body_id)
        self._jb = np.zeros((len(self._bodies), 6, nv))

    def update(self, q: np.ndarray | None = None) -> None:
        """Forward kinematics at configuration q (or the data's current qpos)."""
        if q is not None:
            self.data.qpos[:] = q
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_comPos(self.model, self.data)

    def poses(self, q: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """World positions (N,3) and frames (N,3,3) of all taxels."""
        self.update(q)
        d = self.data
        T = np.empty((4, 3))
        ft2 = self._frames_t.reshape(3 * self.n, 3)
        for bid, sel in self.groups:
            R = d.xmat[bid].reshape(3, 3)
            T[0], T[1:] = d.xpos[bid], R.T
            if isinstance(sel, slice):
                np.matmul(self._lh[sel], T, out=self.positions[sel])
                np.matmul(self._ft[3 * sel.start:3 * sel.stop], R.T, out=ft2[3 * sel.start:3 * sel.stop])
            else:
                self.positions[sel] = self._lh[sel] @ T
                self._frames_t[sel] = self.local_frames[sel].transpose(0, 2, 1) @ R.T
        return self.positions, self.frames

    def jacobians(self, q: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Jacobians (N,6,nv), world positions (N,3) and frames (N,3,3) at q.

        One `mj_jacBody` per skinned body, then one compiled pass over the taxels (`_fill`):
        positions, frames and Jacobians written once each (memory-bound, no per-body GEMM).
        The returned arrays are reused by the next call; copy them to keep them.
        """
        self.update(q)
        d, m = self.data, self.model
        for k, bid in enumerate(self._bodies):
            mujoco.mj_jacBody(m, d, self._jb[k, :3], self._jb[k, 3:], int(bid))
        _fill(self._jb, self._slot, self.body_id, d.xmat, d.xpos, self.local_pos, self.local_frames,
              self.jac, self.positions, self._frames_t)
        return self.jac, self.positions, self.frames

    def jacobians_of(self, index: np.ndarray, q: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Jacobians (K,6,nv), world positions (K,3) and frames (K,3,3) of the taxels `index` only
        (new arrays), for control ticks where few taxels matter: one `mj_jacBody` per skinned
        body, then gathers (no per-body loop over the taxels)."""
        self.update(q)
        d, m = self.data, self.model
        for k, bid in enumerate(self._bodies):
            mujoco.mj_jacBody(m, d, self._jb[k, :3], self._jb[k, 3:], int(bid))
        return _gather(self._jb, self._slot, self.body_id, d.xmat, d.xpos, self.local_pos, self.local_frames,
                       np.asarray(index, dtype=np.intp))

    def jacobians_loop(self, q: np.ndarray | None = None) -> np.ndarray:
        """Reference: one `mj_jac` call per taxel (slow, for benchmarks and tests)."""
        pos, _ = self.poses(q)
        out = np.zeros((self.n, 6, self.model.nv))
        jp, jr = np.zeros((3, self.model.nv)), np.zeros((3, self.model.nv))
        for i in range(self.n):
            mujoco.mj_jac(self.model, self.data, jp, jr, pos[i], int(self.body_id[i]))
            out[i, :3], out[i, 3:] = jp, jr
        return out


@numba.njit(cache=True, nogil=True, inline="always")
def _taxel(i, jb, slot, body_id, xmat, xpos, local_pos, local_frames, J, pos, frame):
    """Taxel i into the views given: its Jacobian `J` (6, nv), the body Jacobian `jb` moved to the
    taxel point (`J_p += J_r x r` column by column, r the world offset from the body origin), its
    world position `pos` (3,) and world frame `frame` (3, 3, columns x, y, z)."""
    b, s = body_id[i], slot[i]
    r0 = xmat[b, 0] * local_pos[i, 0] + xmat[b, 1] * local_pos[i, 1] + xmat[b, 2] * local_pos[i, 2]
    r1 = xmat[b, 3] * local_pos[i, 0] + xmat[b, 4] * local_pos[i, 1] + xmat[b, 5] * local_pos[i, 2]
    r2 = xmat[b, 6] * local_pos[i, 0] + xmat[b, 7] * local_pos[i, 1] + xmat[b, 8] * local_pos[i, 2]
    pos[0], pos[1], pos[2] = r0 + xpos[b, 0], r1 + xpos[b, 1], r2 + xpos[b, 2]
    for a in range(3):
        for c in range(3):
            frame[a, c] = xmat[b, 3 * a] * local_frames[i, 0, c] + xmat[b, 3 * a + 1] * local_frames[i, 1, c] \
                + xmat[b, 3 * a + 2] * local_frames[i, 2, c]
    for j in range(jb.shape[2]):
        wx, wy, wz = jb[s, 3, j], jb[s, 4, j], jb[s, 5, j]
        J[0, j] = jb[s, 0, j] + wy * r2 - wz * r1
        J[1, j] = jb[s, 1, j] + wz * r0 - wx * r2
        J[2, j] = jb[s, 2, j] + wx * r1 - wy * r0
        J[3, j], J[4, j], J[5, j] = wx, wy, wz


@numba.njit(cache=True, nogil=True)
def _gather(jb, slot, body_id, xmat, xpos, local_pos, local_frames, index):
    """jacobians_of's per-taxel part (`_taxel`) for each taxel in `index`, into new arrays."""
    K, n = len(index), len(body_id)
    J, pos, frames = np.empty((K, 6, jb.shape[2])), np.empty((K, 3)), np.empty((K, 3, 3))
    for k in range(K):
        i = index[k]
        if i < 0 or i >= n:
            raise IndexError("jacobians_of: a taxel index is out of range (0 <= index < number of taxels)")
        _taxel(i, jb, slot, body_id, xmat, xpos, local_pos, local_frames, J[k], pos[k], frames[k])
    return J, pos, frames


@numba.njit(cache=True, nogil=True)
def _fill(jb, slot, body_id, xmat, xpos, local_pos, local_frames, J, pos, frames_t):
    """`jacobians`' per-taxel part (`_taxel`) for every taxel, into preallocated arrays (frames
    stored transposed, as `poses` keeps them)."""
    for i in range(len(body_id)):
        _taxel(i, jb, slot, body_id, xmat, xpos, local_pos, local_frames, J[i], pos[i], frames_t[i].T)


def retractability(J: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """How well the robot can move each taxel along its -z: `|J_p^T z|` (N,), m/s per rad/s."""
    z = frames[:, :, 2]
    return np.linalg.norm(np.einsum("nij,ni->nj", J[:, :3, :], z), axis=1)

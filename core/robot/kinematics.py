"""Taxel world poses and Jacobians for all taxels at once.

One MuJoCo body Jacobian per skinned body (`mj_jacBody`), then every taxel on that body gets
`J_p = J_p,body - [r]_x J_r` (r its offset from the body origin, world frame) and `J_r` as is:
one compiled pass over all taxels that writes positions, frames and Jacobians once each
(`taxel_kernels`, imported on the first Jacobian: poses and designs need no compiler).
"""
from __future__ import annotations

import mujoco
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


def taxel_quats(frames: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions in MuJoCo's order (w, x, y, z) of taxel frames, (N, 3, 3) or (N, 9) row-major
    rotation matrices (columns x, y, z), by `mju_mat2Quat` (no scipy to import)."""
    m = np.asarray(frames, float).reshape(-1, 9)
    out = np.zeros((len(m), 4))
    for i, row in enumerate(m):
        mujoco.mju_mat2Quat(out[i], row)
    return out


_kernels = None


def _compiled():
    """`taxel_kernels` (numba), imported on first use and then one global lookup per call."""
    global _kernels
    if _kernels is None:
        from skinsafe.core.robot import taxel_kernels

        _kernels = taxel_kernels
    return _kernels


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

        One `mj_jacBody` per skinned body, then one compiled pass over the taxels (`taxel_kernels.fill`):
        positions, frames and Jacobians written once each (memory-bound, no per-body GEMM).
        The returned arrays are reused by the next call; copy them to keep them.
        """
        self.update(q)
        d, m = self.data, self.model
        for k, bid in enumerate(self._bodies):
            mujoco.mj_jacBody(m, d, self._jb[k, :3], self._jb[k, 3:], int(bid))
        _compiled().fill(self._jb, self._slot, self.body_id, d.xmat, d.xpos, self.local_pos, self.local_frames,
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
        return _compiled().gather(self._jb, self._slot, self.body_id, d.xmat, d.xpos, self.local_pos, self.local_frames,
                       np.asarray(index, dtype=np.intp))

    def jacobians_loop(self, q: np.ndarray | None = None) -> np.ndarray:
        """One `mj_jac` call per taxel: the reference for benchmarks and tests, and the add-on's
        path (no compiler; 9 ms at 2,149 taxels, against 0.7 s for the compiled pass's first call).
        Leaves the world positions and frames in `positions` and `frames`."""
        pos, _ = self.poses(q)
        out = np.zeros((self.n, 6, self.model.nv))
        jp, jr = np.zeros((3, self.model.nv)), np.zeros((3, self.model.nv))
        for i in range(self.n):
            mujoco.mj_jac(self.model, self.data, jp, jr, pos[i], int(self.body_id[i]))
            out[i, :3], out[i, 3:] = jp, jr
        return out


def retractability(J: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """How well the robot can move each taxel along its -z: `|J_p^T z|` (N,), m/s per rad/s."""
    z = frames[:, :, 2]
    return np.linalg.norm(np.einsum("nij,ni->nj", J[:, :3, :], z), axis=1)

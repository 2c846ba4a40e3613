"""The compiled per-taxel passes of `TaxelKinematics.jacobians` and `jacobians_of` (numba).

A module of their own so that `skinsafe.core.robot.kinematics` imports numba only when a Jacobian
is first asked for: poses (the add-on's frame overlay) and everything else about a design need
no compiler, and the Blender extension enables without one.
"""
import numba
import numpy as np


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
def gather(jb, slot, body_id, xmat, xpos, local_pos, local_frames, index):
    """`jacobians_of`'s per-taxel part (`_taxel`) for each taxel in `index`, into new arrays."""
    K, n = len(index), len(body_id)
    J, pos, frames = np.empty((K, 6, jb.shape[2])), np.empty((K, 3)), np.empty((K, 3, 3))
    for k in range(K):
        i = index[k]
        if i < 0 or i >= n:
            raise IndexError("jacobians_of: a taxel index is out of range (0 <= index < number of taxels)")
        _taxel(i, jb, slot, body_id, xmat, xpos, local_pos, local_frames, J[k], pos[k], frames[k])
    return J, pos, frames


@numba.njit(cache=True, nogil=True)
def fill(jb, slot, body_id, xmat, xpos, local_pos, local_frames, J, pos, frames_t):
    """`jacobians`' per-taxel part (`_taxel`) for every taxel, into preallocated arrays (frames
    stored transposed, as `poses` keeps them)."""
    for i in range(len(body_id)):
        _taxel(i, jb, slot, body_id, xmat, xpos, local_pos, local_frames, J[i], pos[i], frames_t[i].T)

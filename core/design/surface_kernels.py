"""Compiled kernels of the body surfaces and of module placement: a bounding-volume hierarchy over
a surface's triangles, exact closest points with interpolated normals, and the geodesic march.

Imported on first use (`Surface`, `place_module`), so enabling the add-on loads no compiler."""
import numba
import numpy as np

LEAF = 4  # triangles per BVH leaf at most


@numba.njit(cache=True, nogil=True)
def build_bvh(lo, hi, centroid):
    """A BVH over boxes (T,3) lo/hi with centres `centroid`: per node its box (2T,3) lo/hi, its
    children (left, right; -1 for a leaf) and its leaf range (start, count) into `order`, the
    triangles by leaf."""
    t = lo.shape[0]
    order = np.arange(t)
    node_lo, node_hi = np.empty((2 * t, 3)), np.empty((2 * t, 3))
    child = np.full((2 * t, 2), -1, np.int64)
    span = np.zeros((2 * t, 2), np.int64)
    stack = [(0, 0, t)]
    n_nodes = 1
    while len(stack):
        node, start, end = stack.pop()
        node_lo[node], node_hi[node] = np.inf, -np.inf
        for j in range(start, end):
            for k in range(3):
                node_lo[node, k] = min(node_lo[node, k], lo[order[j], k])
                node_hi[node, k] = max(node_hi[node, k], hi[order[j], k])
        span[node, 0], span[node, 1] = start, end - start
        if end - start <= LEAF:
            continue
        # split at the middle of the centroids' extent along its longest axis (in place, O(n))
        cmin, cmax = np.full(3, np.inf), np.full(3, -np.inf)
        for j in range(start, end):
            for k in range(3):
                cmin[k] = min(cmin[k], centroid[order[j], k])
                cmax[k] = max(cmax[k], centroid[order[j], k])
        axis = np.argmax(cmax - cmin)
        cut = 0.5 * (cmin[axis] + cmax[axis])
        i, j = start, end - 1
        while i <= j:
            if centroid[order[i], axis] < cut:
                i += 1
            else:
                order[i], order[j] = order[j], order[i]
                j -= 1
        mid = i if start < i < end else (start + end) // 2  # all on one side: halve by count
        child[node, 0], child[node, 1] = n_nodes, n_nodes + 1
        stack.append((n_nodes, start, mid))
        stack.append((n_nodes + 1, mid, end))
        n_nodes += 2
    return node_lo[:n_nodes], node_hi[:n_nodes], child[:n_nodes], span[:n_nodes], order


@numba.njit(cache=True, nogil=True, inline="always")
def _box_d2(x, lo, hi):
    d2 = 0.0
    for k in range(3):
        e = max(lo[k] - x[k], 0.0, x[k] - hi[k])
        d2 += e * e
    return d2


@numba.njit(cache=True, nogil=True, inline="always")
def _on_edge(p, s0, s1, s2, e0, e1, e2, inv):
    """The clamped parameter f of the closest point s + f e on an edge to p, and its squared distance."""
    f = min(max(((p[0] - s0) * e0 + (p[1] - s1) * e1 + (p[2] - s2) * e2) * inv, 0.0), 1.0)
    return f, (p[0] - s0 - f * e0) ** 2 + (p[1] - s1 - f * e1) ** 2 + (p[2] - s2 - f * e2) ** 2


@numba.njit(cache=True, nogil=True, inline="always")
def _on_triangle(x, r):
    """Barycentric weights (u, v, w) of the closest point to x on the packed triangle r (a, ab, ac,
    bc, n/|n|^2, 1/|ab|^2, 1/|ac|^2, 1/|bc|^2) and its squared distance."""
    ap0, ap1, ap2 = x[0] - r[0], x[1] - r[1], x[2] - r[2]
    # barycentric coordinates of the projection onto the plane: (ap x ac).n', (ab x ap).n'
    v = (ap1 * r[8] - ap2 * r[7]) * r[12] + (ap2 * r[6] - ap0 * r[8]) * r[13] + (ap0 * r[7] - ap1 * r[6]) * r[14]
    w = (r[4] * ap2 - r[5] * ap1) * r[12] + (r[5] * ap0 - r[3] * ap2) * r[13] + (r[3] * ap1 - r[4] * ap0) * r[14]
    u = 1.0 - v - w
    if u < 0.0 or v < 0.0 or w < 0.0:  # outside: the best of the three edges
        f, dd = _on_edge(x, r[0], r[1], r[2], r[3], r[4], r[5], r[15])  # a -> b
        u, v, w = 1.0 - f, f, 0.0
        f, d1 = _on_edge(x, r[0] + r[3], r[1] + r[4], r[2] + r[5], r[9], r[10], r[11], r[17])  # b -> c
        if d1 < dd:
            dd, u, v, w = d1, 0.0, 1.0 - f, f
        f, d1 = _on_edge(x, r[0] + r[6], r[1] + r[7], r[2] + r[8], -r[6], -r[7], -r[8], r[16])  # c -> a
        if d1 < dd:
            u, v, w = f, 0.0, 1.0 - f
    q0, q1, q2 = r[0] + v * r[3] + w * r[6], r[1] + v * r[4] + w * r[7], r[2] + v * r[5] + w * r[8]
    return u, v, w, (x[0] - q0) ** 2 + (x[1] - q1) ** 2 + (x[2] - q2) ** 2


@numba.njit(cache=True, nogil=True)
def closest_one(x, q, n, stack, pk, corner_normals, node_lo, node_hi, child, span, order):
    """The exact closest point q (3,) and unit normal n (3,) (corner normals interpolated) on the
    triangles to the point x, by depth-first descent of the BVH (nearer child first, boxes farther
    than the best so far skipped; `stack` has room for every node). Returns (triangle, squared
    distance). `Surface.kernel` holds the arguments after `stack`."""
    best, bt, bu, bv, bw = np.inf, -1, 0.0, 0.0, 0.0
    top = 0
    stack[0] = 0
    while top >= 0:
        node = stack[top]
        top -= 1
        if _box_d2(x, node_lo[node], node_hi[node]) >= best:
            continue
        if child[node, 0] < 0:
            for j in range(span[node, 0], span[node, 0] + span[node, 1]):
                t = order[j]
                u, v, w, d2 = _on_triangle(x, pk[t])
                if d2 < best:
                    best, bt, bu, bv, bw = d2, t, u, v, w
        else:
            a, b = child[node, 0], child[node, 1]
            if _box_d2(x, node_lo[a], node_hi[a]) < _box_d2(x, node_lo[b], node_hi[b]):
                a, b = b, a
            stack[top + 1], stack[top + 2] = a, b  # the nearer one on top
            top += 2
    r = pk[bt]
    nn = 0.0
    for k in range(3):
        q[k] = r[k] + bv * r[3 + k] + bw * r[6 + k]
        n[k] = bu * corner_normals[bt, 0, k] + bv * corner_normals[bt, 1, k] + bw * corner_normals[bt, 2, k]
        nn += n[k] * n[k]
    nn = np.sqrt(nn)
    for k in range(3):
        n[k] /= nn
    return bt, best


@numba.njit(cache=True, nogil=True)
def bvh_closest(p, pk, corner_normals, node_lo, node_hi, child, span, order):
    """`closest_one` for every point p (m,3): points, normals, triangles, squared distances."""
    m = p.shape[0]
    q_out, n_out = np.zeros((m, 3)), np.zeros((m, 3))
    d_out, t_out = np.zeros(m), np.zeros(m, np.int64)
    stack = np.empty(child.shape[0] + 1, np.int64)  # never more entries than nodes
    for i in range(m):
        t_out[i], d_out[i] = closest_one(p[i], q_out[i], n_out[i], stack, pk, corner_normals, node_lo, node_hi,
                                         child, span, order)
    return q_out, n_out, t_out, d_out


@numba.njit(cache=True, nogil=True, inline="always")
def _onto(t, n):
    """t made tangent to the unit normal n and unit (in place)."""
    d = t[0] * n[0] + t[1] * n[1] + t[2] * n[2]
    s = 0.0
    for k in range(3):
        t[k] -= d * n[k]
        s += t[k] * t[k]
    s = max(np.sqrt(s), 1e-300)
    for k in range(3):
        t[k] /= s


@numba.njit(cache=True, nogil=True)
def march(p, n, t, carry, hs, *kernel):
    m, steps = p.shape[0], hs.shape[0]
    P, N, C = np.empty((steps + 1, m, 3)), np.empty((steps + 1, m, 3)), np.empty((steps + 1, m, 3))
    P[0], N[0], C[0] = p, n, carry
    fail = np.full(m, -1, np.int64)
    stack = np.empty(kernel[4].shape[0] + 1, np.int64)
    x, tt = np.empty(3), np.empty(3)
    for i in range(m):
        kappa = 0.0
        tt[:] = t[i]
        for k in range(1, steps + 1):
            h = hs[k - 1]
            kh = min(kappa * h, 1.0)
            reach = h * np.tan(kh) / kh if kh > 1e-9 else h
            for j in range(3):
                x[j] = P[k - 1, i, j] + reach * tt[j]
            closest_one(x, P[k, i], N[k, i], stack, *kernel)
            chord, cos = 0.0, 0.0
            for j in range(3):
                chord += (P[k, i, j] - P[k - 1, i, j]) ** 2
                cos += N[k - 1, i, j] * N[k, i, j]
            chord = np.sqrt(chord)
            if chord < 0.5 * h and fail[i] < 0:
                fail[i] = k
            theta = np.arccos(min(max(cos, -1.0), 1.0))
            half = max(theta / 2, 1e-12)
            arc = chord * half / np.sin(half)
            kappa = theta / arc if arc > 0 else 0.0
            _onto(tt, N[k, i])
            C[k, i] = C[k - 1, i]
            _onto(C[k, i], N[k, i])
    return P, N, C, fail

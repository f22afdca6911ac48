"""The distance's compiled kernels: plain Python that numba compiles (:mod:`service.jit`).

Never called uncompiled on large inputs. The scalar helpers take a triangle as its vertex a's
offset ap = p - a from the point and its edges e0 = b - a, e1 = c - a; the kernels loop over
points, pairs and hierarchy nodes. ``compiled()`` gives them, or None without numba.
"""

from __future__ import annotations

import numpy as np

from ...jit import kernels
from .geometry import _THIN, _TINY

#: Columns of a triangle set up for many points: a (3), e0 (3), e1 (3), unit normal (3).
_ROW = 12


def _triangle_q(apx, apy, apz, e0x, e0y, e0z, e1x, e1y, e1z):
    """Squared distance from a point to a triangle, and the weights (v, w) of the closest point.

    Scalars in and out; (v, w) weigh (b, c). The same regions as :func:`_region_weights`, as
    branches (Ericson's order), and the edges for thin triangles; the distance is formed from
    the residual vector, not from dot products.
    """
    d1 = e0x * apx + e0y * apy + e0z * apz
    d2 = e1x * apx + e1y * apy + e1z * apz
    g00 = e0x * e0x + e0y * e0y + e0z * e0z
    g01 = e0x * e1x + e0y * e1y + e0z * e1z
    g11 = e1x * e1x + e1y * e1y + e1z * e1z
    d3, d4, d5, d6 = d1 - g00, d2 - g01, d1 - g01, d2 - g11
    if d1 <= 0.0 and d2 <= 0.0:
        v, w = 0.0, 0.0
    elif d3 >= 0.0 and d4 <= d3:
        v, w = 1.0, 0.0
    else:
        vc = d1 * d4 - d3 * d2
        if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
            v, w = d1 / max(g00, _TINY), 0.0
        elif d6 >= 0.0 and d5 <= d6:
            v, w = 0.0, 1.0
        else:
            vb = d5 * d2 - d1 * d6
            if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
                v, w = 0.0, d2 / max(g11, _TINY)
            else:
                va = d3 * d6 - d5 * d4
                e43, e56 = d4 - d3, d5 - d6
                if va <= 0.0 and e43 >= 0.0 and e56 >= 0.0:
                    w = e43 / max(e43 + e56, _TINY)
                    v = 1.0 - w
                else:
                    s = max(va + vb + vc, _TINY)
                    v, w = vb / s, vc / s
    rx = apx - v * e0x - w * e1x
    ry = apy - v * e0y - w * e1y
    rz = apz - v * e0z - w * e1z
    q = rx * rx + ry * ry + rz * rz
    if g00 * g11 - g01 * g01 <= _THIN * (g00 + g11) * (g00 + g11):  # thin: try the edges
        t = min(max(d1 / max(g00, _TINY), 0.0), 1.0)  # AB
        rx, ry, rz = apx - t * e0x, apy - t * e0y, apz - t * e0z
        qe = rx * rx + ry * ry + rz * rz
        if not q <= qe:
            q, v, w = qe, t, 0.0
        t = min(max(d2 / max(g11, _TINY), 0.0), 1.0)  # AC
        rx, ry, rz = apx - t * e1x, apy - t * e1y, apz - t * e1z
        qe = rx * rx + ry * ry + rz * rz
        if not q <= qe:
            q, v, w = qe, 0.0, t
        bx, by, bz = apx - e0x, apy - e0y, apz - e0z  # BC
        ex, ey, ez = e1x - e0x, e1y - e0y, e1z - e0z
        ee = ex * ex + ey * ey + ez * ez
        t = min(max((ex * bx + ey * by + ez * bz) / max(ee, _TINY), 0.0), 1.0)
        rx, ry, rz = bx - t * ex, by - t * ey, bz - t * ez
        qe = rx * rx + ry * ry + rz * rz
        if not q <= qe:
            q, v, w = qe, 1.0 - t, t
    return q, v, w


def _triangle_q_only(apx, apy, apz, e0x, e0y, e0z, e1x, e1y, e1z):
    """The squared distance of :func:`_triangle_q` alone, with fewer branches.

    The projection onto the plane when it falls inside the triangle, else the nearest of the
    three clamped edge projections (as the numpy backend's evaluation); thin triangles, where
    the inside test is unreliable, go through :func:`_triangle_q`.
    """
    g00 = e0x * e0x + e0y * e0y + e0z * e0z
    g01 = e0x * e1x + e0y * e1y + e0z * e1z
    g11 = e1x * e1x + e1y * e1y + e1z * e1z
    return _triangle_q_gram(apx, apy, apz, e0x, e0y, e0z, e1x, e1y, e1z, g00, g01, g11)


def _triangle_q_gram(apx, apy, apz, e0x, e0y, e0z, e1x, e1y, e1z, g00, g01, g11):
    """:func:`_triangle_q_only` given the edges' Gram entries (a build's table holds them)."""
    d1 = e0x * apx + e0y * apy + e0z * apz
    d2 = e1x * apx + e1y * apy + e1z * apz
    det = g00 * g11 - g01 * g01
    if det <= _THIN * (g00 + g11) * (g00 + g11):
        q, _, _ = _triangle_q(apx, apy, apz, e0x, e0y, e0z, e1x, e1y, e1z)
        return q
    v = g11 * d1 - g01 * d2  # det times the projection's weights
    w = g00 * d2 - g01 * d1
    if v >= 0.0 and w >= 0.0 and v + w <= det:
        v /= det
        w /= det
        rx, ry, rz = apx - v * e0x - w * e1x, apy - v * e0y - w * e1y, apz - v * e0z - w * e1z
        return rx * rx + ry * ry + rz * rz
    t = min(max(d1 / g00, 0.0), 1.0)  # AB
    rx, ry, rz = apx - t * e0x, apy - t * e0y, apz - t * e0z
    q = rx * rx + ry * ry + rz * rz
    t = min(max(d2 / g11, 0.0), 1.0)  # AC
    rx, ry, rz = apx - t * e1x, apy - t * e1y, apz - t * e1z
    q = min(q, rx * rx + ry * ry + rz * rz)
    bx, by, bz = apx - e0x, apy - e0y, apz - e0z  # BC
    ex, ey, ez = e1x - e0x, e1y - e0y, e1z - e0z
    t = min(max((ex * bx + ey * by + ez * bz) / (ex * ex + ey * ey + ez * ez), 0.0), 1.0)
    rx, ry, rz = bx - t * ex, by - t * ey, bz - t * ez
    return min(q, rx * rx + ry * ry + rz * rz)


def _triangle_row(x, faces, f, T, t):
    """Write triangle f at positions x as row t of the table T. Shape: T (n, _ROW).

    Thin triangles (as in :func:`_triangle_q`) get a zero normal, whose plane bounds nothing:
    the direction of a nearly degenerate cross product is not to be trusted.
    """
    i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
    for a in range(3):
        T[t, a] = x[i0, a]
        T[t, 3 + a] = x[i1, a] - x[i0, a]
        T[t, 6 + a] = x[i2, a] - x[i0, a]
    e0x, e0y, e0z, e1x, e1y, e1z = T[t, 3], T[t, 4], T[t, 5], T[t, 6], T[t, 7], T[t, 8]
    g00 = e0x * e0x + e0y * e0y + e0z * e0z
    g01 = e0x * e1x + e0y * e1y + e0z * e1z
    g11 = e1x * e1x + e1y * e1y + e1z * e1z
    nx, ny, nz = e0y * e1z - e0z * e1y, e0z * e1x - e0x * e1z, e0x * e1y - e0y * e1x
    thin = g00 * g11 - g01 * g01 <= _THIN * (g00 + g11) * (g00 + g11)
    s = 0.0 if thin else 1.0 / np.sqrt(nx * nx + ny * ny + nz * nz)
    T[t, 9], T[t, 10], T[t, 11] = nx * s, ny * s, nz * s


def nearest(x, faces, active, tri, start, y, T, face_out, W, r):
    """The closest candidate of each point, and where it meets it.

    Shape: x (p, 3), faces (f, 3), active (n,) the index's faces, tri (P,) each pair's row of
    ``active``, start (m + 1,), y (m, 3), T (n, _ROW) workspace; writes, per point,
    face_out (m,) the winning face, W (3, m) the closest point's weights on its three nodes
    and r (3, m) the closest point minus the point. A candidate whose plane is already no
    nearer than the best so far cannot beat it and is skipped (the lists come nearest first,
    so the best is usually met first).
    """
    for t in range(active.size):
        _triangle_row(x, faces, active[t], T, t)
    for j in range(y.shape[0]):
        px, py, pz = y[j, 0], y[j, 1], y[j, 2]
        q_best, t_best, v_best, w_best = np.inf, tri[start[j]], 0.0, 0.0
        for k in range(start[j], start[j + 1]):
            t = tri[k]
            apx, apy, apz = px - T[t, 0], py - T[t, 1], pz - T[t, 2]
            h = apx * T[t, 9] + apy * T[t, 10] + apz * T[t, 11]
            if h * h >= q_best:
                continue
            q, v, w = _triangle_q(apx, apy, apz, T[t, 3], T[t, 4], T[t, 5], T[t, 6], T[t, 7], T[t, 8])
            if q < q_best:
                q_best, t_best, v_best, w_best = q, t, v, w
        f = active[t_best]
        u = 1.0 - v_best - w_best
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        face_out[j], W[0, j], W[1, j], W[2, j] = f, u, v_best, w_best
        for a in range(3):
            r[a, j] = x[i0, a] * u + x[i1, a] * v_best + x[i2, a] * w_best - y[j, a]


def spread(faces, face, W, G, grad):
    """grad = sum_j W[k, j] G[:, j] on node faces[face[j], k]. Shape: G (3, m); grad (p, 3)."""
    grad[:] = 0.0
    for j in range(face.size):
        f = face[j]
        for k in range(3):
            i, c = faces[f, k], W[k, j]
            for a in range(3):
                grad[i, a] += c * G[a, j]


def motion(x, x0):
    """max_i |x_i - x0_i|^2, NaN as soon as x holds one. Shape: x, x0 (p, 3) -> float."""
    top = 0.0
    for i in range(x.shape[0]):
        dx, dy, dz = x[i, 0] - x0[i, 0], x[i, 1] - x0[i, 1], x[i, 2] - x0[i, 2]
        q = dx * dx + dy * dy + dz * dz
        if not q <= top:
            if np.isnan(q):
                return q
            top = q
    return top


#: Columns of a triangle in a hierarchy's table: its box (low corner, high corner), a, e0 = b - a,
#: e1 = c - a and the Gram entries e0.e0, e0.e1, e1.e1, so that a build's distance tests read
#: one row instead of gathering three vertices and forming the edges each time.
_TRI = 18


def refit(x, faces, order, span, box, tri):
    """Every triangle's row and every node's box at positions x, leaves first, then upwards.

    Shape: x (p, 3), faces (f, 3), order (f,), span (n, 2); writes tri (f, _TRI), row k for
    triangle order[k], and box (n, 6): low corner, then high corner. An empty leaf gets an
    empty box (+inf low, -inf high), never visited.
    """
    n = span.shape[0]
    n_internal = (n - 1) // 2
    for node in range(n_internal, n):
        for a in range(3):
            box[node, a], box[node, a + 3] = np.inf, -np.inf
        for k in range(span[node, 0], span[node, 1]):
            f = order[k]
            i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
            for a in range(3):
                c0, c1, c2 = x[i0, a], x[i1, a], x[i2, a]
                low, high = min(c0, min(c1, c2)), max(c0, max(c1, c2))
                tri[k, a], tri[k, a + 3] = low, high
                tri[k, 6 + a], tri[k, 9 + a], tri[k, 12 + a] = c0, c1 - c0, c2 - c0
                box[node, a] = min(box[node, a], low)
                box[node, a + 3] = max(box[node, a + 3], high)
            e0x, e0y, e0z, e1x, e1y, e1z = tri[k, 9], tri[k, 10], tri[k, 11], tri[k, 12], tri[k, 13], tri[k, 14]
            tri[k, 15] = e0x * e0x + e0y * e0y + e0z * e0z
            tri[k, 16] = e0x * e1x + e0y * e1y + e0z * e1z
            tri[k, 17] = e1x * e1x + e1y * e1y + e1z * e1z
    for node in range(n_internal - 1, -1, -1):
        left, right = 2 * node + 1, 2 * node + 2
        for a in range(3):
            box[node, a] = min(box[left, a], box[right, a])
            box[node, a + 3] = max(box[left, a + 3], box[right, a + 3])


def _box_q(box, node, px, py, pz):
    """Squared distance from a point to a node's box (0 inside). Scalars out."""
    dx = max(box[node, 0] - px, 0.0, px - box[node, 3])
    dy = max(box[node, 1] - py, 0.0, py - box[node, 4])
    dz = max(box[node, 2] - pz, 0.0, pz - box[node, 5])
    return dx * dx + dy * dy + dz * dz


def candidates(x, faces, order, span, box, tri, y, reach, hint, leaf, face_out, start):
    """Every triangle within d0 + reach of each point, d0 its distance to the surface.

    Shape: x (p, 3), faces (f, 3), order (f,), span (n, 2), box (n, 6), tri (f, _TRI)
    refitted at x, y (m, 3); hint (m,) a face per point likely near it (its last closest), or
    empty; leaf (f,) each face's leaf node; writes face_out (P,) the triangles of point 0, then
    point 1, ..., and start (m + 1,) where each point's begin. Returns P, or -1 when face_out
    is too short (grow it and call again). With u the least distance met so far (u >= d0), a
    node or a triangle whose box is farther than r = u + reach holds no wanted triangle
    (tested when a child is pushed and again when it is visited: u only shrinks); the
    triangles met within r are filtered again at the final u = d0. A relative 1e-9 of slack
    covers roundoff, so a list is the exact one plus at most triangles within that slack of
    its limit. A subtree is searched depth first, nearer child first (the stack never holds
    more than depth + 1 nodes). Without a hint the search is the root's subtree; with one,
    the hint's exact distance bounds d0 before any search, and the search climbs from the
    hint's leaf: that leaf, then the other child of each of its ancestors, from the bottom up,
    which together are the whole tree. The answer is usually near the hint, so the bound
    shrinks at once and most of those subtrees are skipped at their root, about a fifth
    faster than descending from the root (the beam's frames). Lists come sorted nearest
    first, ties by face, so they do not depend on the hints or the visiting order. Squared
    distances are compared first (a hair looser than r, so only the square root decides what
    is kept), and a triangle's square root is taken only when it may be kept.
    """
    n_internal = (span.shape[0] - 1) // 2
    buf_face = np.empty(order.size, np.intp)
    buf_d = np.empty(order.size)
    stack = np.empty(128, np.intp)
    stack_q = np.empty(128)
    pos = 0
    for j in range(y.shape[0]):
        start[j] = pos
        px, py, pz = y[j, 0], y[j, 1], y[j, 2]
        u, nb, node = np.inf, 0, 0
        if hint.size:
            f = hint[j]
            i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
            ax, ay, az = x[i0, 0], x[i0, 1], x[i0, 2]
            u = np.sqrt(_triangle_q_only(
                px - ax, py - ay, pz - az,
                x[i1, 0] - ax, x[i1, 1] - ay, x[i1, 2] - az,
                x[i2, 0] - ax, x[i2, 1] - ay, x[i2, 2] - az,
            ))  # fmt: skip
            node = leaf[f]
        r = u + reach
        r += 1e-9 * r
        rr = r * r * (1.0 + 1e-12)  # the squares' test: never drops what r keeps
        stack[0], stack_q[0], top = node, _box_q(box, node, px, py, pz), 1
        while True:
            while top > 0:  # the subtree on the stack
                top -= 1
                if stack_q[top] > rr:  # u may have shrunk since the push
                    continue
                at = stack[top]
                if at >= n_internal:
                    for k in range(span[at, 0], span[at, 1]):
                        if _box_q(tri, k, px, py, pz) > rr:
                            continue
                        q = _triangle_q_gram(
                            px - tri[k, 6], py - tri[k, 7], pz - tri[k, 8],
                            tri[k, 9], tri[k, 10], tri[k, 11], tri[k, 12], tri[k, 13], tri[k, 14],
                            tri[k, 15], tri[k, 16], tri[k, 17],
                        )  # fmt: skip
                        if q > rr:
                            continue
                        d = np.sqrt(q)
                        if d < u:
                            u = d
                            r = u + reach
                            r += 1e-9 * r
                            rr = r * r * (1.0 + 1e-12)
                        if d <= r:
                            buf_face[nb], buf_d[nb] = order[k], d
                            nb += 1
                else:  # push the children within reach, the nearer last, so visited first
                    left, right = 2 * at + 1, 2 * at + 2
                    q_left, q_right = _box_q(box, left, px, py, pz), _box_q(box, right, px, py, pz)
                    if q_left <= q_right:
                        near, q_near, far, q_far = left, q_left, right, q_right
                    else:
                        near, q_near, far, q_far = right, q_right, left, q_left
                    if q_far <= rr:
                        stack[top], stack_q[top] = far, q_far
                        top += 1
                    if q_near <= rr:
                        stack[top], stack_q[top] = near, q_near
                        top += 1
            if node == 0:
                break
            other = node + 1 if node % 2 == 1 else node - 1  # the other child of node's parent
            node = (node - 1) // 2
            stack[0], stack_q[0], top = other, _box_q(box, other, px, py, pz), 1
        n_kept = 0
        for k in range(nb):  # keep those within d0 + reach
            if buf_d[k] <= r:
                buf_d[n_kept], buf_face[n_kept] = buf_d[k], buf_face[k]
                n_kept += 1
        if pos + n_kept > face_out.size:
            return -1
        if n_kept <= 32:  # nearest first, ties by face: by insertion
            for k in range(1, n_kept):
                d, f, i = buf_d[k], buf_face[k], k
                while i > 0 and (buf_d[i - 1] > d or (buf_d[i - 1] == d and buf_face[i - 1] > f)):
                    buf_d[i], buf_face[i] = buf_d[i - 1], buf_face[i - 1]
                    i -= 1
                buf_d[i], buf_face[i] = d, f
            face_out[pos : pos + n_kept] = buf_face[:n_kept]
        else:  # long lists (far points): by face, then stably by distance
            by_face = np.argsort(buf_face[:n_kept])
            by_d = np.argsort(buf_d[:n_kept][by_face], kind="mergesort")
            face_out[pos : pos + n_kept] = buf_face[:n_kept][by_face][by_d]
        pos += n_kept
    start[y.shape[0]] = pos
    return pos


def activate(face, mark, active, tri):
    """Number the distinct faces of an index in order of appearance. Returns their count n.

    Shape: face (P,), mark (f,) workspace; writes active (n,) the faces and tri (P,) each
    pair's position in ``active``.
    """
    mark[:] = -1
    n = 0
    for k in range(face.size):
        f = face[k]
        if mark[f] < 0:
            mark[f], active[n] = n, f
            n += 1
        tri[k] = mark[f]
    return n


#: The scalar helpers, each after those it calls.
_HELPERS = (_triangle_q, _triangle_q_gram, _triangle_q_only, _triangle_row, _box_q)

#: Each kernel with its one signature (float64 and intp arrays, all C-contiguous), so that it is
#: compiled when a PointToSurface is made (several seconds, or about 0.3 s from numba's disk
#: cache), not in a session's first frame.
compiled = kernels(
    (
        nearest,
        "void(f8[:, ::1], intp[:, ::1], intp[::1], intp[::1], intp[::1], f8[:, ::1], "
        "f8[:, ::1], intp[::1], f8[:, ::1], f8[:, ::1])",
    ),
    (spread, "void(intp[:, ::1], intp[::1], f8[:, ::1], f8[:, ::1], f8[:, ::1])"),
    (motion, "f8(f8[:, ::1], f8[:, ::1])"),
    (refit, "void(f8[:, ::1], intp[:, ::1], intp[::1], intp[:, ::1], f8[:, ::1], f8[:, ::1])"),
    (
        candidates,
        "intp(f8[:, ::1], intp[:, ::1], intp[::1], intp[:, ::1], f8[:, ::1], f8[:, ::1], "
        "f8[:, ::1], f8, intp[::1], intp[::1], intp[::1], intp[::1])",
    ),
    (activate, "intp(intp[::1], intp[::1], intp[::1], intp[::1])"),
    helpers=_HELPERS,
)

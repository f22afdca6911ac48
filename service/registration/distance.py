"""Exact point-to-surface distance of a point cloud, with its gradient in the vertex positions.

The registration objective of one frame is

    J(x) = 1 / (2 m) * sum_j rho(d(y_j, S(x)))

with y_j (m, 3) the frame's cloud, S(x) the matching triangles at vertex positions x and d the
exact Euclidean point-to-triangle distance. By the envelope theorem the closest point c_j (on
triangle t_j, barycentric weights w_j) may be held fixed when differentiating, so
d(d_j^2)/dx_v = 2 (c_j - y_j) w_jv on the three vertices of t_j: the gradient is one weighted
scatter onto the nodes.

:class:`PointToSurface` is evaluated tens of times per frame, so each point only looks at a few
candidate triangles, chosen when an index is built (from a bounding-volume hierarchy in the
compiled backend, a k-d tree over the centroids in the numpy one) and kept while the surface
moves less than a margin; the candidate rule is exact (see the class docstring). Indices and
spatial structures are per-session mutable state: one object per session, never shared between
threads.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import logging
import math
import types
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from .settings import Loss

log = logging.getLogger(__name__)

Array = np.ndarray
Backend = Literal["auto", "numba", "numpy"]

#: A triangle is thin when det G <= _THIN (tr G)^2, G = [[ab.ab, ab.ac], [ab.ac, ac.ac]] its Gram
#: matrix, i.e. when G's condition number exceeds about 1 / _THIN. Face formulas that solve with
#: G lose about eps / _THIN there, so thin triangles also try their three edges, which is exact
#: at zero area (the triangle is then the union of its edges).
_THIN = 1e-6
_TINY = np.finfo(np.float64).tiny
#: Triangles per leaf of the compiled backend's hierarchy (about: leaves hold f / 2^depth).
_LEAF = 8
#: A spatial structure is laid out again once a vertex has moved this many mean edges from
#: where it was laid out. Only speed depends on it: the hierarchy's boxes are refitted, exact,
#: at every build, and the centroid tree's search is widened by the motion.
_RELAYOUT_HIERARCHY = 8.0
_RELAYOUT_TREE = 0.5
_NO_HINT = np.empty(0, np.intp)


# -- one point, one triangle ----------------------------------------------------------------------


def _region_weights(
    d1: Array, d2: Array, g00: Array, g01: Array, g11: Array
) -> tuple[Array, Array]:
    """Barycentric weights (v, w) on (b, c) of the closest point, by Ericson's Voronoi regions.

    Shape: all (n,) -> (n,), (n,). With ab = b - a, ac = c - a, ap = p - a: d1 = ab.ap,
    d2 = ac.ap, g00 = ab.ab, g01 = ab.ac, g11 = ac.ac. Every other dot product of Ericson's
    method follows from these five (bp = ap - ab, cp = ap - ac), so a caller with many points
    per triangle only forms two dot products per pair. Regions are applied from the face up to
    vertex A so that the earliest test of Ericson's sequence wins, as in his branching code.
    Exact for well-shaped triangles; thin ones give finite weights of a point of the triangle,
    not always the closest (see :func:`_weights`).
    """
    d3 = d1 - g00  # ab.bp
    d4 = d2 - g01  # ac.bp
    d5 = d1 - g01  # ab.cp
    d6 = d2 - g11  # ac.cp
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2

    s = va + vb + vc  # the face region: normalise by the sum so that weights stay convex
    np.maximum(s, _TINY, out=s)
    v = vb / s
    w = vc / s

    e43 = d4 - d3  # bc.bp
    e56 = d5 - d6  # -bc.cp
    m = (va <= 0) & (e43 >= 0) & (e56 >= 0)  # edge BC
    t = e43 / np.maximum(e43 + e56, _TINY)
    np.copyto(v, 1.0 - t, where=m)
    np.copyto(w, t, where=m)

    m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)  # edge AC
    np.copyto(v, 0.0, where=m)
    np.copyto(w, d2 / np.maximum(g11, _TINY), where=m)

    m = (d6 >= 0) & (d5 <= d6)  # vertex C
    np.copyto(v, 0.0, where=m)
    np.copyto(w, 1.0, where=m)

    m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)  # edge AB
    np.copyto(v, d1 / np.maximum(g00, _TINY), where=m)
    np.copyto(w, 0.0, where=m)

    m = (d3 >= 0) & (d4 <= d3)  # vertex B
    np.copyto(v, 1.0, where=m)
    np.copyto(w, 0.0, where=m)

    m = (d1 <= 0) & (d2 <= 0)  # vertex A
    np.copyto(v, 0.0, where=m)
    np.copyto(w, 0.0, where=m)
    return v, w


def _squared_distance(
    pp: Array, d1: Array, d2: Array, g00: Array, g01: Array, g11: Array, v: Array, w: Array
) -> Array:
    """|ap - v ab - w ac|^2 from dot products. Shape: all (n,) -> (n,).

    Loses about eps * |ap|^2 to cancellation, which only matters for choosing between two
    triangles whose distances agree to that level; the winner's distance is recomputed from
    vectors.
    """
    return pp - v * (2.0 * d1 - v * g00 - 2.0 * w * g01) - w * (2.0 * d2 - w * g11)


def _segment_weights(
    pp: Array, d1: Array, d2: Array, g00: Array, g01: Array, g11: Array
) -> tuple[Array, Array, Array]:
    """Weights (v, w) and squared distance of the closest point on the three edges.

    Shape: all (n,) -> 3 x (n,). A zero-area triangle is the union of its edges, so this is
    the exact answer there, where the region tests of :func:`_region_weights` are unreliable.
    """
    t_ab = np.clip(d1 / np.maximum(g00, _TINY), 0.0, 1.0)
    q_ab = pp - t_ab * (2.0 * d1 - t_ab * g00)
    t_ac = np.clip(d2 / np.maximum(g11, _TINY), 0.0, 1.0)
    q_ac = pp - t_ac * (2.0 * d2 - t_ac * g11)
    bc2 = g00 - 2.0 * g01 + g11
    bc_bp = d2 - d1 - g01 + g00  # (ac - ab).(ap - ab)
    bp2 = pp - 2.0 * d1 + g00
    t_bc = np.clip(bc_bp / np.maximum(bc2, _TINY), 0.0, 1.0)
    q_bc = bp2 - t_bc * (2.0 * bc_bp - t_bc * bc2)

    v, w, q = t_ab, np.zeros_like(t_ab), q_ab
    m = q_ac < q
    v, w, q = np.where(m, 0.0, v), np.where(m, t_ac, w), np.where(m, q_ac, q)
    m = q_bc < q
    v, w, q = np.where(m, 1.0 - t_bc, v), np.where(m, t_bc, w), np.where(m, q_bc, q)
    return v, w, np.maximum(q, 0.0)


def _is_thin(g00: Array, g01: Array, g11: Array) -> Array:
    """Triangles too thin to trust a solve with their Gram matrix. Shape: (n,) -> (n,) bool."""
    trace = g00 + g11
    return g00 * g11 - g01 * g01 <= _THIN * trace * trace


def _weights(
    pp: Array, d1: Array, d2: Array, g00: Array, g01: Array, g11: Array
) -> tuple[Array, Array, Array]:
    """Weights (v, w) and squared distance for any triangle, degenerate ones included.

    Shape: all (n,) -> 3 x (n,). Thin triangles take the better of the region answer and the
    edges' answer: both are points of the triangle, so the better is never worse than either,
    and at zero area the edges' is exact.
    """
    v, w = _region_weights(d1, d2, g00, g01, g11)
    q = _squared_distance(pp, d1, d2, g00, g01, g11, v, w)
    thin = np.flatnonzero(_is_thin(g00, g01, g11))
    if thin.size:
        sv, sw, sq = _segment_weights(pp[thin], d1[thin], d2[thin], g00[thin], g01[thin], g11[thin])
        better = ~(q[thin] <= sq)  # also replaces a NaN from the region tests
        idx = thin[better]
        v[idx], w[idx], q[idx] = sv[better], sw[better], sq[better]
    return v, w, q


def closest_point_on_triangles(p: Array, a: Array, b: Array, c: Array) -> tuple[Array, Array]:
    """Exact closest point of each point on its triangle, and its barycentric weights.

    Shape: p, a, b, c (N, 3) -> closest (N, 3), bary (N, 3) on (a, b, c).
    All seven Voronoi regions (three vertices, three edges, the face) are handled; zero-area
    triangles (segments, points) give finite, exact answers.

    >>> import numpy as np
    >>> a, b, c = np.eye(3)[None, 0], np.eye(3)[None, 1], np.eye(3)[None, 2]
    >>> closest, bary = closest_point_on_triangles(np.ones((1, 3)), a, b, c)
    >>> np.round(bary, 6).tolist()
    [[0.333333, 0.333333, 0.333333]]
    """
    p, a, b, c = (np.asarray(z, np.float64) for z in (p, a, b, c))
    if p.ndim != 2 or p.shape[1] != 3 or not p.shape == a.shape == b.shape == c.shape:
        raise ValueError(f"p, a, b, c must all be (N, 3), got {[z.shape for z in (p, a, b, c)]}")
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    g00 = np.einsum("ij,ij->i", ab, ab)
    g01 = np.einsum("ij,ij->i", ab, ac)
    g11 = np.einsum("ij,ij->i", ac, ac)
    pp = np.einsum("ij,ij->i", ap, ap)
    v, w, _ = _weights(pp, d1, d2, g00, g01, g11)
    closest = a + v[:, None] * ab + w[:, None] * ac
    return closest, np.stack([1.0 - v - w, v, w], axis=1)


# -- compiled kernels -----------------------------------------------------------------------------
#
# Plain Python that numba compiles (see :func:`_compiled`), never called uncompiled on large
# inputs. The scalar helpers take a triangle as its vertex a's offset ap = p - a from the point
# and its edges e0 = b - a, e1 = c - a.

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


def _nearest_loop(x, faces, active, tri, start, y, T, face_out, W, r):
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
            q, v, w = _triangle_q(
                apx, apy, apz, T[t, 3], T[t, 4], T[t, 5], T[t, 6], T[t, 7], T[t, 8]
            )
            if q < q_best:
                q_best, t_best, v_best, w_best = q, t, v, w
        f = active[t_best]
        u = 1.0 - v_best - w_best
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        face_out[j], W[0, j], W[1, j], W[2, j] = f, u, v_best, w_best
        for a in range(3):
            r[a, j] = x[i0, a] * u + x[i1, a] * v_best + x[i2, a] * w_best - y[j, a]


def _spread(faces, face, W, G, grad):
    """grad = sum_j W[k, j] G[:, j] on node faces[face[j], k]. Shape: G (3, m); grad (p, 3)."""
    grad[:] = 0.0
    for j in range(face.size):
        f = face[j]
        for k in range(3):
            i, c = faces[f, k], W[k, j]
            for a in range(3):
                grad[i, a] += c * G[a, j]


def _max_motion(x, x0):
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


def _bvh_refit(x, faces, order, span, box, tri):
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


def _bvh_candidates(x, faces, order, span, box, tri, y, reach, hint, leaf, face_out, start):
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


def _activate(face, mark, active, tri):
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


#: The kernels, each with its one signature: float64 and intp arrays, all C-contiguous.
_KERNELS = {
    "nearest": (
        _nearest_loop,
        (
            "void(f8[:, ::1], intp[:, ::1], intp[::1], intp[::1], intp[::1], f8[:, ::1], "
            "f8[:, ::1], intp[::1], f8[:, ::1], f8[:, ::1])"
        ),
    ),
    "spread": (_spread, "void(intp[:, ::1], intp[::1], f8[:, ::1], f8[:, ::1], f8[:, ::1])"),
    "motion": (_max_motion, "f8(f8[:, ::1], f8[:, ::1])"),
    "refit": (
        _bvh_refit,
        "void(f8[:, ::1], intp[:, ::1], intp[::1], intp[:, ::1], f8[:, ::1], f8[:, ::1])",
    ),
    "candidates": (
        _bvh_candidates,
        (
            "intp(f8[:, ::1], intp[:, ::1], intp[::1], intp[:, ::1], f8[:, ::1], f8[:, ::1], "
            "f8[:, ::1], f8, intp[::1], intp[::1], intp[::1], intp[::1])"
        ),
    ),
    "activate": (_activate, "intp(intp[::1], intp[::1], intp[::1], intp[::1])"),
}


@functools.cache
def _compiled() -> types.SimpleNamespace:
    """The kernels compiled by numba; ImportError without numba.

    Compiled eagerly for their one signature each, so the cost (several seconds, or about
    0.3 s from numba's disk cache) falls when a session is set up rather than in its first
    frame. The scalar helpers are compiled first and bound into the kernels that call them.
    """
    import numba

    log.info("compiling (or loading) the point-to-triangle kernels, numba %s", numba.__version__)
    jit = functools.partial(numba.njit, cache=True, nogil=True)
    helpers: dict = {}
    for helper in _HELPERS:  # in order: a helper may call the ones before it
        helpers[helper.__name__] = jit(inline="always")(_rebind(helper, helpers))
    kernels = {
        name: jit(signature)(_rebind(source, helpers))
        for name, (source, signature) in _KERNELS.items()
    }
    return types.SimpleNamespace(**kernels)


def _rebind(source, helpers: dict):
    """``source`` with the named globals bound to ``helpers``, for numba to compile.

    numba resolves a kernel's globals when it compiles it, and calls compiled functions only;
    binding the compiled helpers here, rather than decorating at import, keeps numba an import
    of first use and the plain functions plain. The code object is the source's own, so
    numba's disk cache (keyed on the file and the function's name) still finds it.
    """
    scope = dict(source.__globals__, **helpers)
    fn = types.FunctionType(source.__code__, scope, source.__name__, source.__defaults__)
    fn.__module__, fn.__qualname__, fn.__doc__ = (
        source.__module__,
        source.__qualname__,
        source.__doc__,
    )
    return fn


def numba_available() -> bool:
    """Whether the compiled kernels can be used (numba importable)."""
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


# -- a cloud against a moving surface -------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Closest:
    """Where each cloud point meets the surface, for reporting.

    Shape: distance (m,), points (m, 3) closest surface points, face (m,) row of the
    constructor's ``faces``, bary (m, 3) weights on that face's nodes, kept (m,) bool (False
    for the points the trimmed loss ignores).
    """

    distance: Array
    points: Array
    face: Array
    bary: Array
    kept: Array

    @property
    def sq_distances(self) -> Array:
        """Squared distances. Shape: (m,)."""
        return self.distance**2

    @property
    def rms(self) -> float:
        """Root-mean-square distance over all points (trimmed ones included)."""
        return float(np.sqrt(np.mean(self.distance**2)))


@dataclasses.dataclass(frozen=True)
class Match:
    """Where each point met the surface at the last evaluation, as the evaluation had it:
    the Gauss-Newton model's input, at no extra search.

    Shape: x (p, 3) the positions evaluated; face (m,); W (3, m) weights on the face's nodes;
    r (3, m) closest point minus point; weight (m,) each point's factor in dJ/dc_j = weight r_j
    (1/m for the squared loss; 0 for points the trimmed loss leaves out).
    """

    x: Array
    face: Array
    W: Array
    r: Array
    weight: Array


@dataclasses.dataclass(frozen=True)
class _Index:
    """Candidate pairs (point, triangle) of one build.

    Pairs are sorted by point: point j owns pairs start[j] : start[j + 1]. The numpy backend
    also lays them out for vectorised evaluation (``slot``, ``width``, ``y``).
    """

    x0: Array  # (p, 3) positions at the build
    margin: float  # the index is exact while no vertex has moved more than this from x0
    face: Array  # (P,) row of faces of each pair
    start: Array  # (m + 1,) first pair of each point, then P
    tri: Array  # (P,) the same, as a position in `active`
    active: Array  # (T,) every face that is some point's candidate
    nodes: Array  # (q,) sorted nodes of those faces: the gradient is zero on every other node
    slot: Array | None = None  # (P,) flat position in an (m, width) table; None if lists are full
    width: int = 0  # length of the longest candidate list
    y: Array | None = None  # (3, P) each pair's point, coordinates first

    @property
    def n_pairs(self) -> int:
        return int(self.face.size)


@dataclasses.dataclass(frozen=True)
class _Hierarchy:
    """A bounding-volume hierarchy over the triangles, for the compiled backend.

    Its topology (``order``, ``span``: see :func:`_bvh_layout`) is chosen once at positions x0
    and kept; ``box`` is refitted at the current positions before every use, so its bounds are
    exact whatever the motion, and the motion since x0 only costs query speed.
    """

    x0: Array  # (p, 3) positions when the topology was chosen
    edge: float  # mean edge length there
    order: Array  # (f,) triangles, leaf by leaf
    span: Array  # (n, 2) each node's range of order
    box: Array  # (n, 6) each node's box, refitted in place
    tri: Array  # (f, _TRI) each triangle's box and edges, in order, refitted with them
    leaf: Array  # (f,) each triangle's leaf node


@dataclasses.dataclass(frozen=True)
class _CentreTree:
    """A k-d tree over the triangles' centroids at positions x0, for the numpy backend.

    Kept while the surface moves less than a tolerance from x0: every distance it returns is
    then wrong by at most that motion, which the search widens by (see the class docstring of
    :class:`PointToSurface`).
    """

    x0: Array  # (p, 3) positions at the build
    edge: float  # mean edge length there
    tree: cKDTree  # over the centroids g_t(x0)
    g: Array  # (3, f) the centroids g_t(x0), coordinates first
    radius: Array  # (f,) r_t = max_k |v_k(x0) - g_t(x0)|, each triangle's bounding radius


class PointToSurface:
    """J(x) = 1/(2m) sum_j rho(d(y_j, S(x))) and dJ/dx, with an exact candidate index.

    Shape: faces (f, 3) node ids of a larger mesh. ``nodes`` (p,) are the sorted ids these faces
    use and ``faces`` is kept renumbered into 0..p-1; every ``x`` argument holds the positions
    of exactly ``nodes``, in this order, (p, 3).

    ``loss`` picks rho: ``"squared"`` rho(d) = d^2; ``"huber"`` d^2 up to ``delta`` (a length)
    and 2 delta d - delta^2 beyond; ``"trimmed"`` d^2 with the fraction ``trim`` (default 0.1)
    of farthest points left out, J then being 1/(2 m_kept) times the sum over the m_kept others.
    ``loss_param`` is either parameter under one name (delta for huber, trim for trimmed;
    ignored for squared), as a session's config holds it.
    ``margin`` is the index's margin M, a length; by default ``margin_factor`` times the mean
    edge length where the spatial structure was last laid out (a quarter edge: about 7
    candidates per point on the liver). ``keep`` is how many of a frame's indices are kept for
    reuse, so that a line search that probes far and comes back does not rebuild.
    ``backend`` is ``"numba"`` (the compiled kernels), ``"numpy"`` (the vectorised reference)
    or ``"auto"`` (numba when it imports). ``n_builds`` counts the indices built (at least one
    per frame, more when the surface moves beyond the margin), ``n_one_off`` those of them
    built for a lone evaluation (margin 0, see ``_lookup``), ``n_layouts`` the spatial
    structures laid out (rarely: they are kept across frames). All three only ever grow.

    >>> import trimesh
    >>> sphere = trimesh.creation.icosphere(subdivisions=2)
    >>> S = PointToSurface(sphere.faces, backend="numpy")
    >>> S.bind(2.0 * sphere.vertices[:10])  # each point 1 away from the surface
    >>> J, grad = S(sphere.vertices[S.nodes])
    >>> round(2 * J, 12), grad.shape
    (1.0, (162, 3))

    Why the candidate rule is exact: a build at positions x0 gives point y every triangle t
    with d(y, T_t(x0)) <= d0(y) + 2 M, where d0 is y's distance to the surface and M the margin.
    While no vertex has moved more than delta <= M from x0, no point of any triangle has (it is
    a convex combination of its vertices), so every point-triangle distance has changed by at
    most delta. A triangle left out is then farther than d0 + 2M - delta >= d0 + delta, and the
    triangle closest at x0 is now at most d0 + delta away: a left-out triangle is never the
    closest, and the minimum over the candidates is the minimum over the surface. The argument
    only involves x0 and the current positions, so any index of the frame may serve any
    evaluation within its margin of its x0, whatever was evaluated in between: an evaluation
    uses the last used of the ``keep`` kept indices that qualifies, and builds a new one at the
    current positions when none does. M = 0 is allowed: such a one-off index holds each
    point's closest triangles and is exact at its own positions only; it is built for an
    evaluation far from where the surface has been (only speed depends on that choice).

    How a build finds those triangles without looking at all of them. Compiled backend: a
    bounding-volume hierarchy whose topology is kept across frames and whose boxes are refitted
    at the build's positions, so each box contains its triangles exactly, whatever the motion
    since the layout. Each point descends nearer child first; with u the least exact distance
    met so far (u >= d0), a box (or a triangle's own box) farther than u + 2M holds no
    triangle within d0 + 2M and is skipped; the triangles met within u + 2M are filtered again
    at the final u = d0. Numpy backend: a k-d tree over the centroids g_t, at positions x1
    within delta of the build's (kept across frames while delta is small). The triangle of a
    point's nearest centroid gives an upper bound U on d0. Since d(y, T_t(x0)) >= |y - g_t(x1)|
    - r_t(x1) - delta, r_t the bounding radius around g_t, a triangle with |y - g_t(x1)| above
    U + 2M + r_t + delta cannot qualify; the tree returns the others (a ball of radius U + 2M +
    max r_t + delta), whose exact distances then decide. Both keep a relative 1e-9 of slack
    against roundoff. Evaluation: the compiled loop skips a candidate whose plane is no nearer
    than the best so far (the distance to the plane bounds the distance to the triangle from
    below), which never skips a nearer one, up to roundoff.
    """

    def __init__(
        self,
        faces: Array,
        *,
        loss: Loss = "squared",
        delta: float | None = None,
        trim: float | None = None,
        loss_param: float | None = None,
        margin: float | None = None,
        margin_factor: float = 0.25,
        backend: Backend = "auto",
        keep: int = 3,
    ) -> None:
        faces = np.asarray(faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise ValueError(f"faces must be a non-empty (f, 3) array, got shape {faces.shape}")
        if not np.issubdtype(faces.dtype, np.integer) or faces.min() < 0:
            raise ValueError("faces must hold non-negative integer node ids")
        if loss not in ("squared", "huber", "trimmed"):
            raise ValueError(f"loss must be 'squared', 'huber' or 'trimmed', got {loss!r}")
        if loss_param is not None and loss != "squared":  # the one-number form of a config
            if (delta if loss == "huber" else trim) is not None:
                raise ValueError(f"give {loss}'s parameter once: loss_param or its own name")
            delta, trim = (loss_param, trim) if loss == "huber" else (delta, loss_param)
        trim = 0.1 if trim is None else trim
        if loss == "huber" and not (delta is not None and np.isfinite(delta) and delta > 0):
            raise ValueError("the huber loss needs a positive threshold delta (a length)")
        if loss == "trimmed" and not 0.0 <= trim < 1.0:
            raise ValueError(f"trim must lie in [0, 1), got {trim}")
        if margin is not None and not (np.isfinite(margin) and margin > 0):
            raise ValueError(f"margin must be a positive length, got {margin}")
        if not margin_factor > 0:
            raise ValueError(f"margin_factor must be positive, got {margin_factor}")
        if not (isinstance(keep, (int, np.integer)) and keep >= 1):
            raise ValueError(f"keep must be a positive number of indices, got {keep!r}")
        if backend not in ("auto", "numba", "numpy"):
            raise ValueError(f"backend must be 'auto', 'numba' or 'numpy', got {backend!r}")
        if backend == "auto":
            backend = "numba" if numba_available() else "numpy"
        self._kernels = _compiled() if backend == "numba" else None  # ImportError here
        self.backend = backend
        self.nodes, local = np.unique(faces, return_inverse=True)
        self.faces = np.ascontiguousarray(local.reshape(faces.shape), dtype=np.intp)
        self._columns = np.ascontiguousarray(self.faces.T)  # (3, f): contiguous for take
        self.loss, self.delta, self.trim = loss, delta, trim
        self.margin, self.margin_factor = margin, margin_factor
        self.points: Array | None = None
        self._yt: Array | None = None  # the points, coordinates first (3, m)
        self.keep = int(keep)
        self.n_builds = 0  # candidate indices built (at least one per frame)
        self.n_one_off = 0  # ... of which one-offs (margin 0, see _lookup)
        self.n_layouts = 0  # spatial structures (hierarchy or centroid tree) built
        self._indices: list[_Index] = []  # this frame's, the last used first
        self._footprints: list[tuple[Array, bool]] = []  # x0 of recent indices, with a margin?
        self._spaces: list[_Hierarchy | _CentreTree] = []  # kept across frames, last used first
        self._capacity = 0  # pairs the compiled build's buffer holds
        self._last: tuple | None = None  # the last evaluation's match, as last_match gives it
        self._uniform: Array | None = None  # the points' one weight (squared loss), per cloud
        self._hint = _NO_HINT  # each point's last closest face this frame (compiled builds)

    @property
    def _index(self) -> _Index | None:
        """The index of the last evaluation (None before the first one of a frame)."""
        return self._indices[0] if self._indices else None

    @property
    def n_nodes(self) -> int:
        return int(self.nodes.size)

    @property
    def gradient_nodes(self) -> Array | None:
        """The nodes (rows of x) of the last evaluation's candidate triangles: its gradient is
        zero on every other row, so a model's pullback may read out through these alone. The
        same array object while the index lives (a cache key). None before an evaluation."""
        return None if self._index is None else self._index.nodes

    @property
    def last_match(self) -> Match | None:
        """Where each point met the surface at the last evaluation of this frame (None before
        one): what a Gauss-Newton model needs, without another search."""
        if self._last is None:
            return None
        x, face, W, r, coef, _ = self._last
        if np.ndim(coef) == 0:  # one weight for all: the frame's array of it, made once
            if self._uniform is None or self._uniform[0] != coef:
                self._uniform = np.full(face.size, coef)
                self._uniform.flags.writeable = False
            coef = self._uniform
        return Match(x, face, W, r, coef)

    @property
    def last_rms(self) -> float:
        """The RMS distance of all points (trimmed ones too) at the last evaluation of this
        frame (NaN before one): a frame's report at its best iterate, without another search."""
        return math.nan if self._last is None else math.sqrt(self._last[5] / self._last[1].size)

    @property
    def n_pairs(self) -> int:
        """Candidate pairs in the current index (0 before the first evaluation of a frame)."""
        return 0 if self._index is None else self._index.n_pairs

    # -- frame ------------------------------------------------------------------------------------

    def bind(self, points: Array) -> None:
        """Set this frame's cloud; the index is rebuilt at the next evaluation.

        Shape: points (m, 3), m >= 1, finite.
        """
        y = np.asarray(points, dtype=np.float64)
        if y.ndim != 2 or y.shape[1] != 3 or len(y) == 0:
            raise ValueError(f"points must be a non-empty (m, 3) array, got shape {y.shape}")
        if not np.isfinite(y).all():
            raise ValueError("points contain NaN or infinite coordinates")
        self.points = np.array(y, order="C")  # our own writable copy: the caller's array may be
        self._yt = np.ascontiguousarray(y.T)  # a read-only view of a message buffer
        self._indices = []
        self._footprints = [(x0, full) for x0, full in self._footprints if full]
        self._last = self._uniform = None
        self._hint = _NO_HINT

    # -- evaluation -------------------------------------------------------------------------------

    def __call__(self, x: Array) -> tuple[float, Array]:
        """The objective and its exact gradient. Shape: x (p, 3) -> float, (p, 3)."""
        x = self._check(x)
        face, W, r = self._nearest(x)
        q = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
        m, total = q.size, float(q.sum())
        if self.loss == "squared":
            J = total / (2 * m)
            coef = 1.0 / m
        elif self.loss == "huber":
            d = np.sqrt(q)
            far = d > self.delta
            J = float(np.where(far, 2.0 * self.delta * d - self.delta**2, q).sum()) / (2 * m)
            coef = np.where(far, self.delta / np.maximum(d, self.delta), 1.0) / m
        else:
            kept = self._kept(q)
            n_kept = int(np.count_nonzero(kept))
            J = float(q[kept].sum()) / (2 * n_kept)
            coef = kept / n_kept
        G = r * coef  # (3, m): dJ/dc_j, which bary spreads on the face's nodes
        self._last = (x, face, W, r, coef, total)
        grad = np.empty((self.n_nodes, 3))
        if self._kernels is not None:
            self._kernels.spread(self.faces, face, W, G, grad)
            return J, grad
        idx = self._columns.take(face, axis=1).ravel()
        for axis in range(3):  # three bincounts over (3 m,) beat one over broadcast (m, 3, 3)
            grad[:, axis] = np.bincount(idx, (W * G[axis]).ravel(), minlength=self.n_nodes)
        return J, grad

    def closest(self, x: Array) -> Closest:
        """Closest surface point of every cloud point, for reporting. Shape: x (p, 3)."""
        x = self._check(x)
        face, W, r = self._nearest(x)
        q = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
        kept = self._kept(q) if self.loss == "trimmed" else np.ones(q.size, bool)
        points = np.ascontiguousarray((self._yt + r).T)
        return Closest(np.sqrt(q), points, face, np.ascontiguousarray(W.T), kept)

    def _check(self, x: Array) -> Array:
        if self.points is None:
            raise RuntimeError("bind a point cloud before evaluating")
        x = np.ascontiguousarray(x, dtype=np.float64)
        if x.shape != (self.n_nodes, 3):
            raise ValueError(f"x must have shape ({self.n_nodes}, 3), got {x.shape}")
        return x

    def _kept(self, q: Array) -> Array:
        """The points the trimmed loss keeps: all but the floor(trim m) farthest."""
        m = q.size
        n_kept = m - int(np.floor(self.trim * m))
        kept = np.zeros(m, bool)
        kept[np.argpartition(q, n_kept - 1)[:n_kept]] = True
        return kept

    def _nearest(self, x: Array) -> tuple[Array, Array, Array]:
        """Where each point meets the surface: face, weights on its nodes, c_j - y_j.

        Shape: x (p, 3) -> face (m,) a row of ``faces``, W (3, m), r (3, m); the face's three
        nodes or the coordinates first, so every later step is a row operation. Uses an index
        of this frame still exact at x, or builds one (see :meth:`_lookup`). The residual is
        formed from the vertices, not from dot products.
        """
        ix = self._lookup(x)
        m = len(self.points)
        W, r = np.empty((3, m)), np.empty((3, m))
        if self._kernels is not None:
            face = np.empty(m, np.intp)
            T = np.empty((ix.active.size, _ROW))
            self._kernels.nearest(
                x, self.faces, ix.active, ix.tri, ix.start, self.points, T, face, W, r
            )
            self._hint = face  # the next build's first guesses
            return face, W, r
        face, v, w = self._nearest_numpy(x, ix)
        nodes = self._columns.take(face, axis=1)
        xt = x.T
        np.subtract(1.0 - v, w, out=W[0])
        W[1], W[2] = v, w
        np.multiply(xt.take(nodes[0], axis=1), W[0], out=r)
        r += xt.take(nodes[1], axis=1) * v
        r += xt.take(nodes[2], axis=1) * w
        r -= self._yt
        return face, W, r

    def _nearest_numpy(self, x: Array, ix: _Index) -> tuple[Array, Array, Array]:
        """The vectorised reference: every candidate pair at once, then a row-wise argmin.

        Face or edges rather than Ericson's seven regions (fewer array passes): the closest
        point is the projection onto the plane when that falls inside the triangle, else the
        nearest of the three clamped edge projections. Per-triangle constants are formed once
        for the active triangles and gathered per pair as one take, coordinates first, so each
        later step is a 1-D ufunc over the pairs. Squared distances come from dot products
        (about eps |y - a|^2 of cancellation, enough to choose); the caller recomputes the
        winner's from vectors.
        """
        nodes = self.faces.take(ix.active, axis=0)  # (T, 3)
        X = np.ascontiguousarray(x.T).take(nodes, axis=1)  # (axis, triangle, vertex)
        F = np.empty((19, X.shape[1]))
        a = X[:, :, 0]
        F[0:3] = a
        e0 = np.subtract(X[:, :, 1], a, out=F[3:6])
        e1 = np.subtract(X[:, :, 2], a, out=F[6:9])
        g00 = np.einsum("ij,ij->j", e0, e0, out=F[9])
        g11 = np.einsum("ij,ij->j", e1, e1, out=F[10])
        g01 = np.einsum("ij,ij->j", e0, e1)
        np.divide(1.0, np.maximum(g00, _TINY), out=F[11])
        np.divide(1.0, np.maximum(g11, _TINY), out=F[12])
        np.subtract(g00, g01, out=F[13])  # bc.(b - a) with the sign that bc_bp below needs
        bc2 = np.add(F[13], g11 - g01, out=F[14])
        np.divide(1.0, np.maximum(bc2, _TINY), out=F[15])
        det = g00 * g11 - g01 * g01
        thin = _is_thin(g00, g01, g11)
        idet = 1.0 / np.maximum(det, _TINY)
        idet[thin] = np.nan  # their face answer is replaced below; NaN, unlike inf, stays quiet
        np.multiply(g00, idet, out=F[16])
        np.multiply(g01, idet, out=F[17])
        np.multiply(g11, idet, out=F[18])

        P = F.take(ix.tri, axis=1)  # (19, n_pairs)
        ap = ix.y - P[0:3]
        d1 = P[3] * ap[0]
        d1 += P[4] * ap[1]
        d1 += P[5] * ap[2]
        d2 = P[6] * ap[0]
        d2 += P[7] * ap[1]
        d2 += P[8] * ap[2]
        pp = ap[0] * ap[0]
        pp += ap[1] * ap[1]
        pp += ap[2] * ap[2]
        s = P[18] * d1 - P[17] * d2  # barycentric (v, w) of the projection onto the plane
        t = P[16] * d2 - P[17] * d1
        inside = (s >= 0) & (t >= 0) & (s + t <= 1)
        q = pp - s * d1 - t * d2
        t_ab = _unit_clamp(d1 * P[11])
        q_ab = pp - t_ab * (2.0 * d1 - t_ab * P[9])
        t_ac = _unit_clamp(d2 * P[12])
        q_ac = pp - t_ac * (2.0 * d2 - t_ac * P[10])
        bc_bp = d2 - d1 + P[13]
        t_bc = _unit_clamp(bc_bp * P[15])
        q_bc = (pp - 2.0 * d1 + P[9]) - t_bc * (2.0 * bc_bp - t_bc * P[14])
        np.copyto(q, np.minimum(np.minimum(q_ab, q_ac), q_bc), where=~inside)
        if thin.any():  # thin triangles: the region method with its edge fallback
            sel = np.flatnonzero(thin[ix.tri])
            g01p = g01[ix.tri[sel]]
            sv, sw, sq = _weights(pp[sel], d1[sel], d2[sel], P[9, sel], g01p, P[10, sel])
            inside[sel], s[sel], t[sel], q[sel] = True, sv, sw, sq

        if ix.slot is None:
            k = q.reshape(-1, ix.width).argmin(axis=1)
        else:
            table = np.full((len(ix.start) - 1) * ix.width, np.inf)
            table[ix.slot] = q
            k = table.reshape(-1, ix.width).argmin(axis=1)
        best = ix.start[:-1] + k
        v, w = s[best], t[best]  # right where the winner's projection is inside its face
        edge = np.stack([q_ab[best], q_ac[best], q_bc[best]]).argmin(axis=0)
        out = ~inside[best]
        on_ab, on_ac, on_bc = out & (edge == 0), out & (edge == 1), out & (edge == 2)
        v[on_ab], w[on_ab] = t_ab[best[on_ab]], 0.0
        v[on_ac], w[on_ac] = 0.0, t_ac[best[on_ac]]
        v[on_bc], w[on_bc] = 1.0 - t_bc[best[on_bc]], t_bc[best[on_bc]]
        return ix.face[best], v, w

    # -- index ------------------------------------------------------------------------------------

    def _lookup(self, x: Array) -> _Index:
        """An index exact at x: the last used one still within its margin of x, else a new one.

        Line searches probe a point and come back: the ``keep`` indices of this frame last used
        are tried in that order, so coming back costs a motion check (a few microseconds), not
        a build. Any of them is exact at x by the margin argument of the class docstring,
        whatever positions were evaluated in between. A new index gets the margin M only where
        the surface dwells (see :meth:`_dwells`); elsewhere, it is a one-off: margin 0, exact
        at x alone (and so reused only at the same x, e.g. by ``closest`` after a call), about
        a third of the cost since each point then looks no farther than its closest triangle.
        """
        for i, ix in enumerate(self._indices):
            moved = self._motion(x, ix.x0)
            if not np.isfinite(moved):
                raise ValueError("x contains NaN or infinite coordinates")
            if moved <= ix.margin * ix.margin:
                if i:
                    self._indices.insert(0, self._indices.pop(i))
                return ix
        if not self._indices and not np.isfinite(x).all():
            raise ValueError("x contains NaN or infinite coordinates")
        space = self._space_at(x)
        M = self._margin(space.edge, x)
        ix = self._build(x, space, M if self._dwells(x, M) else 0.0)
        self._indices = [ix, *self._indices[: self.keep - 1]]
        self._footprints = [(ix.x0, ix.margin > 0), *self._footprints[: self.keep - 1]]
        return ix

    def _dwells(self, x: Array, M: float) -> bool:
        """Whether the surface dwells near x, so that an index with a margin will pay.

        Yes at a session's first evaluation, and when x lies within M of where a recent index
        was built: a one-off of this frame (the evaluation came back near it), or one with a
        margin of this frame or an earlier one (a new frame starts where the last one ended).
        A lone far evaluation, such as the engine's rest state or a line search's probe, gets
        a one-off. Only speed depends on this rule.
        """
        if not self._footprints:  # the first evaluation of a session: nothing known yet
            return True
        return any(self._motion(x, x0) <= M * M for x0, _ in self._footprints)

    def _motion(self, x: Array, x0: Array) -> float:
        """max_i |x_i - x0_i|^2, not finite when x holds a NaN or infinity. Shape: (p, 3) each."""
        if self._kernels is not None:
            return self._kernels.motion(x, x0)
        dx = x - x0
        dx *= dx
        return float((dx[:, 0] + dx[:, 1] + dx[:, 2]).max())

    def _margin(self, edge: float, x: Array) -> float:
        """The margin M: the one given, else margin_factor mean edges (edge: the mean edge)."""
        if self.margin is not None:
            return float(self.margin)
        M = self.margin_factor * edge
        if not M > 0:  # every triangle collapsed to a point: any positive length will do
            M = self.margin_factor * max(float(np.ptp(x, axis=0).max()), 1.0)
        return M

    def _space_at(self, x: Array) -> _Hierarchy | _CentreTree:
        """A spatial structure laid out near x: a kept one, else a new one laid out at x.

        Two are kept, so that evaluations alternating between two far places (the engine's
        rest state and the current frame) do not lay one out each time.
        """
        tolerance = _RELAYOUT_TREE if self._kernels is None else _RELAYOUT_HIERARCHY
        for i, space in enumerate(self._spaces):
            if self._motion(x, space.x0) <= (tolerance * space.edge) ** 2:
                if i:
                    self._spaces.insert(0, self._spaces.pop(i))
                return space
        space = self._centre_tree(x) if self._kernels is None else self._hierarchy(x)
        self._spaces = [space, *self._spaces[:1]]
        return space

    def _build(self, x: Array, space: _Hierarchy | _CentreTree, M: float) -> _Index:
        """Candidate pairs at positions x: every triangle within d0 + 2 M of each point."""
        if self._kernels is not None:
            face, start = self._candidates_compiled(x, space, M)
        else:
            face, start = self._candidates_numpy(x, space, M)
        self.n_builds += 1
        self.n_one_off += M == 0
        m = len(start) - 1
        log.debug("index %d: margin %.3g, %.1f pairs per point", self.n_builds, M, face.size / m)
        if self._kernels is not None:
            active, tri = np.empty(face.size, np.intp), np.empty(face.size, np.intp)
            n = self._kernels.activate(face, np.empty(len(self.faces), np.intp), active, tri)
            active = active[:n]
            return _Index(x0=x.copy(), margin=M, face=face, start=start, tri=tri, active=active,
                          nodes=self._nodes_of(active))
        count = np.diff(start)
        rows = np.repeat(np.arange(m), count)
        width = int(count.max())
        used = np.zeros(len(self.faces), np.intp)
        used[face] = 1
        tri = np.cumsum(used).take(face) - 1  # position of each pair's face among the used
        used = np.flatnonzero(used)
        full = bool((count == width).all())
        return _Index(
            x0=x.copy(),
            margin=M,
            face=face,
            start=start,
            tri=tri,
            active=used,
            nodes=self._nodes_of(used),
            slot=None if full else rows * width + (np.arange(face.size) - start.take(rows)),
            width=width,
            y=self._yt.take(rows, axis=1),
        )

    def _nodes_of(self, active: Array) -> Array:
        """The sorted nodes of these faces (the index's gradient nodes)."""
        mark = np.zeros(self.n_nodes, bool)
        mark[self.faces.take(active, axis=0)] = True
        return np.flatnonzero(mark)

    def _candidates_compiled(self, x: Array, h: _Hierarchy, M: float) -> tuple[Array, Array]:
        """Face (P,) and start (m + 1,) of a build, from the hierarchy refitted at x."""
        K = self._kernels
        K.refit(x, self.faces, h.order, h.span, h.box, h.tri)
        m = len(self.points)
        start = np.empty(m + 1, np.intp)
        self._capacity = max(self._capacity, 16 * m)
        while True:
            face = np.empty(self._capacity, np.intp)
            n = K.candidates(
                x, self.faces, h.order, h.span, h.box, h.tri, self.points, 2 * M, self._hint,
                h.leaf, face, start,
            )  # fmt: skip
            if n >= 0:
                return face[:n], start
            self._capacity *= 4

    def _hierarchy(self, x: Array) -> _Hierarchy:
        """A new hierarchy laid out at positions x (see :func:`_bvh_layout`)."""
        A, B, C = (x.take(self._columns[k], axis=0) for k in range(3))  # (f, 3) each
        order, span = _bvh_layout((A + B + C) / 3.0, _LEAF)
        f = len(self.faces)
        leaves = np.arange((len(span) - 1) // 2, len(span))  # their spans tile order, in order
        leaf = np.empty(f, np.intp)
        leaf[order] = np.repeat(leaves, span[leaves, 1] - span[leaves, 0])
        self.n_layouts += 1
        return _Hierarchy(
            x0=x.copy(),
            edge=_mean_edge(A, B, C),
            order=order,
            span=span,
            box=np.empty((len(span), 6)),
            tri=np.empty((f, _TRI)),
            leaf=leaf,
        )

    def _candidates_numpy(self, x: Array, tree: _CentreTree, M: float) -> tuple[Array, Array]:
        """Face (P,) and start (m + 1,) of a build, from the centroid tree (laid out near x)."""
        yt = self._yt
        m = yt.shape[1]
        delta = np.sqrt(self._motion(x, tree.x0))

        # an upper bound on each point's distance: the triangle of its nearest (old) centroid
        _, near = tree.tree.query(self.points, k=1)
        U = np.sqrt(self._pair_sq(x, np.arange(m + 1), near))

        # every triangle whose old bounding sphere, grown by delta, comes within U + 2M
        bound = U + 2 * M + 1e-9 * (M + U)  # a hair of slack against roundoff
        reach_max = tree.radius.max() + delta
        hits = tree.tree.query_ball_point(self.points, bound + reach_max, return_sorted=False)
        count = np.fromiter(map(len, hits), dtype=np.intp, count=m)
        rows = np.repeat(np.arange(m), count)
        face = np.fromiter(itertools.chain.from_iterable(hits), dtype=np.intp, count=count.sum())
        reach = bound.take(rows) + tree.radius.take(face) + delta
        keep = _norm2(yt.take(rows, axis=1) - tree.g.take(face, axis=1)) <= reach * reach
        rows, face = rows[keep], face[keep]
        start = np.searchsorted(rows, np.arange(m + 1))  # no empty list: see the class docstring
        d = np.sqrt(self._pair_sq(x, start, face))
        d0 = np.minimum.reduceat(d, start[:-1])
        keep = d <= (d0 + 2 * M + 1e-9 * (M + d0)).take(rows)
        rows, face = rows[keep], face[keep]
        return face, np.searchsorted(rows, np.arange(m + 1))

    def _centre_tree(self, x: Array) -> _CentreTree:
        """A k-d tree over the centroids at positions x, with each triangle's bounding radius."""
        xt = np.ascontiguousarray(x.T)
        A, B, C = (xt.take(self._columns[k], axis=1) for k in range(3))  # (3, f) each
        g = (A + B + C) / 3.0
        radius = np.sqrt(np.maximum(np.maximum(_norm2(A - g), _norm2(B - g)), _norm2(C - g)))
        self.n_layouts += 1
        return _CentreTree(
            x0=x.copy(),
            edge=_mean_edge(A.T, B.T, C.T),
            tree=cKDTree(g.T, balanced_tree=False, compact_nodes=False),
            g=g,
            radius=radius,
        )

    def _pair_sq(self, x: Array, start: Array, face: Array) -> Array:
        """Squared distance of each pair: point j against faces[start[j] : start[j + 1]].

        Shape: start (m + 1,), face (P,) -> (P,).
        """
        rows = np.repeat(np.arange(len(start) - 1), np.diff(start))
        nodes = self._columns.take(face, axis=1)
        p = self.points.take(rows, axis=0)
        c, _ = closest_point_on_triangles(p, *(x.take(nodes[k], axis=0) for k in range(3)))
        return np.einsum("ij,ij->i", c - p, c - p)


def _norm2(z: Array) -> Array:
    """Squared length of each column. Shape: (3, n) -> (n,)."""
    return z[0] * z[0] + z[1] * z[1] + z[2] * z[2]


def _bvh_layout(g: Array, leaf: int) -> tuple[Array, Array]:
    """A balanced bounding-volume hierarchy's topology: median splits of the centroids.

    Shape: g (f, 3) triangle centroids -> order (f,) the triangles, leaf by leaf, and
    span (2^(depth+1) - 1, 2) each node's range of ``order``, depth the least with at most
    ``leaf`` triangles a leaf. Node i has children 2i + 1 and 2i + 2; the last 2^depth nodes
    are the leaves. Each node splits its range in halves along the longest axis of its
    centroids, a whole level at a time, so every leaf holds f / 2^depth triangles (more than
    leaf / 2), give or take one.
    """
    f = len(g)
    depth = max(0, int(np.ceil(np.log2(f / leaf))))
    order = np.arange(f)
    span = np.empty((2 ** (depth + 1) - 1, 2), np.intp)
    span[0] = 0, f
    for level in range(depth):
        nodes = np.arange(2**level - 1, 2 ** (level + 1) - 1)
        lo, hi = span[nodes, 0], span[nodes, 1]  # consecutive ranges covering 0..f, none empty
        owner = np.repeat(np.arange(nodes.size), hi - lo)  # (f,) each position's node
        G = g[order]
        axis = (np.maximum.reduceat(G, lo) - np.minimum.reduceat(G, lo)).argmax(axis=1)
        order = order[np.lexsort((G[np.arange(f), axis[owner]], owner))]
        mid = lo + (hi - lo + 1) // 2
        span[2 * nodes + 1, 0], span[2 * nodes + 1, 1] = lo, mid
        span[2 * nodes + 2, 0], span[2 * nodes + 2, 1] = mid, hi
    return np.ascontiguousarray(order, dtype=np.intp), span


def _mean_edge(A: Array, B: Array, C: Array) -> float:
    """Mean edge length of triangles (A, B, C). Shape: (f, 3) each -> float."""
    total = sum(np.sqrt(np.einsum("ij,ij->i", e, e)).sum() for e in (B - A, C - B, A - C))
    return float(total) / (3 * len(A))


def _unit_clamp(t: Array) -> Array:
    """Clamp to [0, 1] in place (np.clip costs more on small arrays)."""
    np.maximum(t, 0.0, out=t)
    return np.minimum(t, 1.0, out=t)

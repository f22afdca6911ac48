"""One point against one triangle, vectorised over pairs: the exact closest point and its weights.

The NumPy reference of the distance: Ericson's Voronoi regions from five dot products per pair
(:func:`_region_weights`), with thin triangles also tried against their three edges, which is
exact at zero area. The compiled kernels (:mod:`.kernels`) do the same one pair at a time.
"""

from __future__ import annotations

import numpy as np

Array = np.ndarray

#: A triangle is thin when det G <= _THIN (tr G)^2, G = [[ab.ab, ab.ac], [ab.ac, ac.ac]] its Gram
#: matrix, i.e. when G's condition number exceeds about 1 / _THIN. Face formulas that solve with
#: G lose about eps / _THIN there, so thin triangles also try their three edges, which is exact
#: at zero area (the triangle is then the union of its edges).
_THIN = 1e-6
_TINY = np.finfo(np.float64).tiny


def _region_weights(d1: Array, d2: Array, g00: Array, g01: Array, g11: Array) -> tuple[Array, Array]:
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


def _squared_distance(pp: Array, d1: Array, d2: Array, g00: Array, g01: Array, g11: Array, v: Array, w: Array) -> Array:
    """|ap - v ab - w ac|^2 from dot products. Shape: all (n,) -> (n,).

    Loses about eps * |ap|^2 to cancellation, which only matters for choosing between two
    triangles whose distances agree to that level; the winner's distance is recomputed from
    vectors.
    """
    return pp - v * (2.0 * d1 - v * g00 - 2.0 * w * g01) - w * (2.0 * d2 - w * g11)


def _segment_weights(pp: Array, d1: Array, d2: Array, g00: Array, g01: Array, g11: Array) -> tuple[Array, Array, Array]:
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


def _weights(pp: Array, d1: Array, d2: Array, g00: Array, g01: Array, g11: Array) -> tuple[Array, Array, Array]:
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


def _norm2(z: Array) -> Array:
    """Squared length of each column. Shape: (3, n) -> (n,)."""
    return z[0] * z[0] + z[1] * z[1] + z[2] * z[2]


def _mean_edge(A: Array, B: Array, C: Array) -> float:
    """Mean edge length of triangles (A, B, C). Shape: (f, 3) each -> float."""
    total = sum(np.sqrt(np.einsum("ij,ij->i", e, e)).sum() for e in (B - A, C - B, A - C))
    return float(total) / (3 * len(A))


def _unit_clamp(t: Array) -> Array:
    """Clamp to [0, 1] in place (np.clip costs more on small arrays)."""
    np.maximum(t, 0.0, out=t)
    return np.minimum(t, 1.0, out=t)

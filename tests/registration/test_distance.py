"""Point-to-triangle distance and the indexed point-to-surface objective.

Closest points are checked against exact answers built region by region and against an
independent reference (plane projection if inside, else the nearest clamped edge); the indexed
objective against an all-pairs evaluation, before and after the surface moves; the gradient
against central differences.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from service.registration.distance import (
    PointToSurface,
    closest_point_on_triangles,
    numba_available,
)
from tests.conftest import LIVER, needs_liver

BACKENDS = [
    "numpy",
    pytest.param("numba", marks=pytest.mark.skipif(not numba_available(), reason="no numba")),
]


# -- references -----------------------------------------------------------------------------------


def segment_closest(p, a, b):
    """Closest point of p on segment ab, row by row (a == b allowed)."""
    ab = b - a
    L = np.einsum("ij,ij->i", ab, ab)
    t = np.where(L > 0, np.einsum("ij,ij->i", p - a, ab) / np.where(L > 0, L, 1.0), 0.0)
    return a + np.clip(t, 0.0, 1.0)[:, None] * ab


def reference_closest(p, a, b, c):
    """Projection onto the plane when it lies inside the triangle, else the nearest edge point.

    Independent of the module's region logic; exact for any triangle (the edges cover the
    zero-area case, where the plane is undefined).
    """
    edges = [segment_closest(p, a, b), segment_closest(p, b, c), segment_closest(p, c, a)]
    dist = np.stack([np.linalg.norm(e - p, axis=1) for e in edges])
    best = np.take_along_axis(np.stack(edges), dist.argmin(0)[None, :, None], 0)[0]
    G = np.stack([b - a, c - a], axis=2)  # (N, 3, 2)
    gram = np.einsum("nia,nib->nab", G, G)
    ok = np.linalg.det(gram) > 1e-9 * np.einsum("naa->n", gram) ** 2
    st = np.zeros((len(p), 2))
    st[ok] = np.linalg.solve(gram[ok], np.einsum("nia,ni->na", G[ok], (p - a)[ok])[..., None])[..., 0]
    inside = ok & (st >= 0).all(1) & (st.sum(1) <= 1)
    proj = a + np.einsum("nia,na->ni", G, st)
    return np.where(inside[:, None], proj, best)


def brute_distance(faces, x, y):
    """Distance of every point to the whole surface, all pairs. Shape: (m,)."""
    m, f = len(y), len(faces)
    p = np.repeat(y, f, axis=0)
    a, b, c = (np.tile(x[faces[:, k]], (m, 1)) for k in range(3))
    closest, _ = closest_point_on_triangles(p, a, b, c)
    return np.linalg.norm(closest - p, axis=1).reshape(m, f).min(axis=1)


def random_triangles(rng, n):
    a, b, c = rng.normal(size=(3, n, 3))
    return a, b, c


def blob(subdivisions=3, seed=0):
    """A lumpy closed surface (an icosphere, stretched and dented) with its vertex positions."""
    rng = np.random.default_rng(seed)
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    v = np.asarray(sphere.vertices) * [1.0, 0.7, 0.5]
    v *= 1.0 + 0.1 * np.sin(3 * v[:, :1]) * np.cos(2 * v[:, 1:2])
    v += 0.01 * rng.normal(size=v.shape)
    return v, np.asarray(sphere.faces)


def cloud_near(x, faces, rng, m, spread=0.05):
    """Points scattered around random surface points, a few of them far away."""
    t = rng.integers(len(faces), size=m)
    w = rng.dirichlet(np.ones(3), size=m)
    y = np.einsum("mk,mki->mi", w, x[faces[t]]) + spread * rng.normal(size=(m, 3))
    y[: m // 20] *= 1.8
    return y


# -- one point, one triangle ----------------------------------------------------------------------


def test_closest_point_exact_in_each_of_the_seven_regions():
    rng = np.random.default_rng(1)
    n = 200
    a, b, c = random_triangles(rng, n)
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    z = rng.normal(size=(n, 1))  # any height above or below the plane
    s = rng.uniform(0.1, 2.0, size=(n, 1))
    unit = lambda v: v / np.linalg.norm(v, axis=1, keepdims=True)  # noqa: E731

    cases = []  # (points, expected closest, expected bary)
    for i, (p, q, r) in enumerate([(a, b, c), (b, c, a), (c, a, b)]):
        outward = -(unit(q - p) + unit(r - p))  # into the vertex's region, for any triangle
        bary = np.zeros((n, 3))
        bary[:, i] = 1.0
        cases.append((p + s * outward + z * normal, p, bary))
        mid = (p + q) / 2  # the edge pq, beyond it in the plane: the midpoint is closest
        out = np.cross(q - p, normal)
        out *= np.sign(np.einsum("ij,ij->i", out, p - r))[:, None]
        bary = np.zeros((n, 3))
        bary[:, i] = bary[:, (i + 1) % 3] = 0.5
        cases.append((mid + s * unit(out) + z * normal, mid, bary))
    w = rng.dirichlet(np.ones(3), size=n) * 0.7 + 0.1  # face: inside, every weight >= 0.1
    inner = np.einsum("nk,kni->ni", w, np.stack([a, b, c]))
    cases.append((inner + z * normal, inner, w))

    for points, expected, bary_expected in cases:
        closest, bary = closest_point_on_triangles(points, a, b, c)
        np.testing.assert_allclose(closest, expected, atol=1e-12)
        np.testing.assert_allclose(bary, bary_expected, atol=1e-12)
        np.testing.assert_allclose(np.einsum("nk,kni->ni", bary, np.stack([a, b, c])), closest)


def test_closest_point_matches_reference_on_random_points():
    rng = np.random.default_rng(2)
    n = 5000
    a, b, c = random_triangles(rng, n)
    a[:50] *= [1.0, 1.0, 1e-3]  # some thin and obtuse ones
    p = 2.0 * rng.normal(size=(n, 3))
    closest, bary = closest_point_on_triangles(p, a, b, c)
    ref = reference_closest(p, a, b, c)
    np.testing.assert_allclose(np.linalg.norm(closest - p, axis=1), np.linalg.norm(ref - p, axis=1), atol=1e-12)
    np.testing.assert_allclose(closest, ref, atol=1e-9)
    assert (bary >= -1e-12).all() and np.allclose(bary.sum(1), 1.0)
    supports = {tuple(row) for row in (bary > 1e-12)}
    assert len(supports) == 7  # three vertices, three edges and the face were all reached


def test_closest_point_not_beaten_by_dense_sampling():
    rng = np.random.default_rng(3)
    a, b, c = random_triangles(rng, 20)
    p = 2.0 * rng.normal(size=(20, 3))
    closest, _ = closest_point_on_triangles(p, a, b, c)
    d = np.linalg.norm(closest - p, axis=1)
    u, v = np.meshgrid(np.linspace(0, 1, 101), np.linspace(0, 1, 101))
    keep = u + v <= 1
    u, v = u[keep], v[keep]
    samples = a[:, None] + u[:, None] * (b - a)[:, None] + v[:, None] * (c - a)[:, None]
    d_samples = np.linalg.norm(samples - p[:, None], axis=2).min(axis=1)
    assert (d <= d_samples + 1e-12).all()
    assert (d_samples - d < 0.05).all()


def test_degenerate_triangles_give_finite_exact_answers():
    line = np.array([[0.0, 0, 0], [1, 1, 1], [3, 3, 3]])  # collinear, c beyond b
    cases = [
        line,
        line[[0, 2, 1]],
        np.array([[0.0, 0, 0], [0, 0, 0], [1, 2, 3]]),  # two vertices coincide
        np.array([[1.0, 1, 1], [2, 0, 0], [1, 1, 1]]),
        np.array([[0.5, -1, 2]] * 3),  # a point
        np.array([[0.0, 0, 0], [1, 0, 0], [2, 1e-12, 0]]),  # almost a segment
    ]
    rng = np.random.default_rng(4)
    p = 3.0 * rng.normal(size=(300, 3))
    for tri in cases:
        a, b, c = (np.repeat(v[None], len(p), axis=0) for v in tri)
        closest, bary = closest_point_on_triangles(p, a, b, c)
        assert np.isfinite(closest).all() and np.isfinite(bary).all()
        np.testing.assert_allclose(bary.sum(1), 1.0)
        np.testing.assert_allclose(
            np.linalg.norm(closest - p, axis=1),
            np.linalg.norm(reference_closest(p, a, b, c) - p, axis=1),
            atol=1e-9,
        )


def test_closest_point_refuses_mismatched_shapes():
    with pytest.raises(ValueError):
        closest_point_on_triangles(np.zeros((2, 3)), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)))


# -- a cloud against a surface --------------------------------------------------------------------


@pytest.mark.parametrize("backend", BACKENDS)
def test_points_at_radius_two_are_one_from_the_unit_sphere(backend):
    sphere = trimesh.creation.icosphere(subdivisions=3)
    rng = np.random.default_rng(5)
    d = rng.normal(size=(400, 3))
    y = 2.0 * d / np.linalg.norm(d, axis=1, keepdims=True)
    S = PointToSurface(np.asarray(sphere.faces), backend=backend)
    S.bind(y)
    res = S.closest(np.asarray(sphere.vertices)[S.nodes])
    np.testing.assert_allclose(res.distance, 1.0, atol=5e-3)  # the facets sit inside the sphere
    assert (res.distance >= 1.0 - 1e-12).all()
    np.testing.assert_allclose(np.linalg.norm(res.points, axis=1), 1.0, atol=5e-3)


@pytest.mark.parametrize("backend", BACKENDS)
def test_indexed_distance_equals_brute_force_while_the_surface_moves(backend):
    rng = np.random.default_rng(6)
    x, faces = blob()
    y = cloud_near(x, faces, rng, 300)
    S = PointToSurface(faces, backend=backend)
    S.bind(y)
    np.testing.assert_allclose(S.closest(x).distance, brute_distance(faces, x, y), atol=1e-12)
    assert S.n_builds == 1
    margin = S._index.margin

    for _ in range(3):  # small moves: the index stays, the answers stay exact
        x_small = x + rng.uniform(-1, 1, size=x.shape) * margin / np.sqrt(3) * 0.99
        res = S.closest(x_small)
        np.testing.assert_allclose(res.distance, brute_distance(faces, x_small, y), atol=1e-12)
        J, _ = S(x_small)
        assert J == pytest.approx(np.mean(res.distance**2) / 2, rel=1e-12)
    assert S.n_builds == 1

    x_edge = x.copy()  # the refresh rule: any vertex beyond the margin
    x_edge[7] += [0.99 * margin, 0.0, 0.0]
    S(x_edge)
    assert S.n_builds == 1
    x_edge[7] += [0.02 * margin, 0.0, 0.0]
    S(x_edge)
    assert S.n_builds == 2

    x_big = x + 0.05 * rng.normal(size=x.shape) + [0.02, 0.0, -0.03]  # forces a refresh
    np.testing.assert_allclose(S.closest(x_big).distance, brute_distance(faces, x_big, y), atol=1e-12)
    assert S.n_builds == 3
    S.bind(y[::2])  # a new frame rebuilds
    np.testing.assert_allclose(S.closest(x_big).distance, brute_distance(faces, x_big, y[::2]), atol=1e-12)
    assert S.n_builds == 4


def all_pairs(faces, x, y):
    """Distance of every point to every triangle. Shape: (m, f)."""
    m, f = len(y), len(faces)
    p = np.repeat(y, f, axis=0)
    a, b, c = (np.tile(x[faces[:, k]], (m, 1)) for k in range(3))
    closest, _ = closest_point_on_triangles(p, a, b, c)
    return np.linalg.norm(closest - p, axis=1).reshape(m, f)


def assert_exact_candidates(S, x):
    """The current index holds, per point, exactly the triangles within d0 + 2M at its build.

    Up to the builds' relative 1e-9 of slack at the limit; x must be the build's positions.
    """
    ix = S._index
    np.testing.assert_array_equal(ix.x0, x)
    D = all_pairs(S.faces, x, S.points)
    limit = D.min(axis=1, keepdims=True) + 2 * ix.margin
    slack = 1e-9 * limit
    for j in range(len(D)):
        got = set(ix.face[ix.start[j] : ix.start[j + 1]].tolist())
        assert got >= set(np.flatnonzero(D[j] <= limit[j] - slack[j]).tolist())
        assert got <= set(np.flatnonzero(D[j] <= limit[j] + slack[j]).tolist())
    np.testing.assert_array_equal(ix.active[ix.tri], ix.face)


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradient_lives_on_the_gradient_nodes(backend):
    """A pullback may read out through gradient_nodes alone: the gradient is zero elsewhere,
    and the array is the same object while the index lives (the pullback's cache key)."""
    rng = np.random.default_rng(11)
    x, faces = blob()
    S = PointToSurface(faces, backend=backend)
    assert S.gradient_nodes is None
    S.bind(cloud_near(x, faces, rng, 40)[:10])  # a few points: most nodes get no gradient
    _, grad = S(x)
    rows = S.gradient_nodes
    assert 0 < rows.size < S.n_nodes and np.all(np.diff(rows) > 0)
    off = np.setdiff1d(np.arange(S.n_nodes), rows)
    assert np.all(grad[off] == 0) and np.any(grad[rows] != 0)
    S(x + 1e-9)  # well within the margin: same index, same object
    assert S.gradient_nodes is rows
    S(x + 0.3)  # far: a new index, a new node set
    assert S.gradient_nodes is not rows


@pytest.mark.parametrize("backend", BACKENDS)
def test_candidates_are_exactly_those_within_the_margin(backend):
    """Near, far and clustered points, and lists long enough to grow the build's buffer."""
    rng = np.random.default_rng(14)
    x, faces = blob(subdivisions=2)
    y = np.concatenate(
        [
            cloud_near(x, faces, rng, 60),
            5.0 * rng.normal(size=(10, 3)),  # far away: long lists
            np.zeros((40, 3)) + 1e-3 * rng.normal(size=(40, 3)),  # clustered at the centre
            np.repeat(x[faces[:5, 0]], 4, axis=0),  # on vertices, four times each
            (x[faces[5:10, 0]] + x[faces[5:10, 1]]) / 2,  # on edges
        ]
    )
    S = PointToSurface(faces, backend=backend)
    S.bind(y)
    np.testing.assert_allclose(S.closest(x).distance, brute_distance(faces, x, y), atol=1e-12)
    assert_exact_candidates(S, x)
    assert S.n_pairs > 16 * len(y)  # the compiled build's first buffer was too short


def flat_grid(n):
    """Equilateral triangles of unit edge tiling a flat patch. Shape: x (n^2, 3), faces."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    x = np.stack([i + 0.5 * j, j * np.sqrt(3) / 2, 0.0 * i], axis=-1).reshape(-1, 3)
    ids = np.arange(n * n).reshape(n, n)
    a, b, c, d = ids[:-1, :-1], ids[1:, :-1], ids[:-1, 1:], ids[1:, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1), np.stack([b, d, c], -1)]).reshape(-1, 3)
    return x, faces


@pytest.mark.parametrize("backend", BACKENDS)
def test_candidates_stay_exact_when_the_surface_slides_under_a_kept_structure(backend):
    """Congruent triangles and points on their centroids leave the builds' bounds no slack."""
    rng = np.random.default_rng(17)
    x, faces = flat_grid(12)
    centroids = x[faces].mean(axis=1)
    for _ in range(12):
        S = PointToSurface(faces, backend=backend, margin=rng.uniform(0.2, 1.0))
        y = centroids[rng.choice(len(faces), 40)]
        S.bind(y)
        S.closest(x)
        angle = rng.uniform(0, 2 * np.pi)  # slide it in its plane, less than half an edge
        x_slid = x + 0.2475 * np.array([np.cos(angle), np.sin(angle), 0.0])
        S.bind(y)
        S.closest(x_slid)
        assert S.n_layouts == 1
        assert_exact_candidates(S, x_slid)


@pytest.mark.parametrize("backend", BACKENDS)
def test_spatial_structure_is_kept_across_frames_and_small_motion(backend):
    rng = np.random.default_rng(15)
    x, faces = blob(subdivisions=2)
    S = PointToSurface(faces, backend=backend)
    for k in range(4):  # frames: a new cloud, a surface that moved a little (about a margin)
        x_k = x + 0.005 * k * rng.normal(size=x.shape)
        y = cloud_near(x_k, faces, rng, 80)
        S.bind(y)
        np.testing.assert_allclose(S.closest(x_k).distance, brute_distance(faces, x_k, y), atol=1e-12)
        assert_exact_candidates(S, x_k)
    assert (S.n_builds, S.n_layouts) == (4, 1)

    x_far = x + [30.0, 0.0, 0.0]  # far beyond any tolerance: laid out again, still exact
    S.bind(y)
    d = S.closest(x_far).distance
    np.testing.assert_allclose(d, brute_distance(faces, x_far, y), atol=1e-12)
    assert (S.n_builds, S.n_layouts) == (5, 2)


@pytest.mark.parametrize("backend", BACKENDS)
def test_probes_that_come_back_reuse_their_index(backend):
    rng = np.random.default_rng(16)
    x, faces = blob(subdivisions=2)
    y = cloud_near(x, faces, rng, 100)
    step = rng.normal(size=x.shape)
    S = PointToSurface(faces, backend=backend)
    S.bind(y)
    J0, g0 = S(x)  # a session's first evaluation: an index with a margin
    M = S._index.margin
    assert M > 0 and (S.n_builds, S.n_one_off) == (1, 0)
    step *= 3 * M / np.abs(step).max()  # a probe three margins away
    sequence = [  # t, builds, of which one-offs
        (1.0, 2, 1),  # a lone probe: a one-off
        (0.0, 2, 1),  # back within the first index's margin
        (0.2, 2, 1),
        (1.0, 2, 1),  # the same probe again: its one-off
        (0.5, 3, 2),
        (0.0, 3, 2),
        (2.0, 4, 3),  # the probe at 1.0, least recently used, is dropped
        (1.0, 5, 3),  # ... so built again, with a margin: the surface came back near it
        (1.1, 5, 3),  # within that margin
    ]
    for t, builds, one_off in sequence:
        x_t = x + t * step
        J, grad = S(x_t)
        assert (S.n_builds, S.n_one_off) == (builds, one_off), t
        assert J == pytest.approx(np.mean(brute_distance(faces, x_t, y) ** 2) / 2, rel=1e-12)
        if t == 0.0:
            assert J == J0 and np.array_equal(grad, g0)
    assert len(S.candidates._indices) == 3

    once = PointToSurface(faces, backend=backend, keep=1)  # one index: every return rebuilds
    once.bind(y)
    for t in (0.0, 1.0, 0.0, 1.0):
        once(x + t * step)
    assert once.n_builds == 4


@pytest.mark.parametrize("backend", BACKENDS)
def test_lone_evaluations_get_one_off_indices(backend):
    """A frame that starts where the last one ended gets a margin at once; a lone far
    evaluation (the engine's rest state) a one-off, which ``closest`` at the same x reuses."""
    rng = np.random.default_rng(18)
    x, faces = blob(subdivisions=2)
    S = PointToSurface(faces, backend=backend)
    S.bind(cloud_near(x, faces, rng, 60))
    S(x)  # a session's first evaluation: an index with a margin
    x_far = x + 0.3
    for frame in range(1, 4):
        x_k = x + 0.002 * frame * rng.normal(size=x.shape)
        y = cloud_near(x_k, faces, rng, 60)
        S.bind(y)
        n = S.n_builds
        d_far = S.closest(x_far).distance  # far from anything built: a one-off
        J, _ = S(x_far)  # the same x: reused
        assert (S.n_builds - n, S._index.margin) == (1, 0.0)
        assert J == pytest.approx(np.mean(d_far**2) / 2, rel=1e-12)
        np.testing.assert_allclose(d_far, brute_distance(faces, x_far, y), atol=1e-12)
        S(x_k)  # near where the last frame dwelt: a margin at once
        assert S.n_builds - n == 2 and S._index.margin > 0
        S(x_k + 0.1 * S._index.margin)
        assert S.n_builds - n == 2
    assert S.n_one_off == 3
    assert S.n_layouts == (2 if backend == "numpy" else 1)  # a centroid tree for each place

    x_near = x_far + 1e-3 * rng.normal(size=x.shape)  # a one-off serves its own x only
    S(x_far)
    assert S.n_builds - n == 2
    np.testing.assert_allclose(S.closest(x_near).distance, brute_distance(faces, x_near, y), atol=1e-12)
    assert S.n_builds - n == 3 and S._index.margin > 0  # the surface came back near it
    with pytest.raises(ValueError):
        PointToSurface(faces, keep=0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_surface_with_zero_area_triangles_equals_brute_force(backend):
    rng = np.random.default_rng(12)
    x, faces = blob(subdivisions=2)
    n = len(x)
    a = 1.5 * rng.normal(size=(30, 3))  # loose segments and points around the blob
    b = a + 0.3 * rng.normal(size=(30, 3))
    x = np.concatenate([x, a, b, (a + b) / 2])
    ia, ib, im = n + np.arange(30), n + 30 + np.arange(30), n + 60 + np.arange(30)
    extra = [
        np.stack([ia, ia, ib], 1)[:10],  # two vertices coincide
        np.stack([ia, ib, ib], 1)[10:20],
        np.stack([ia, ib, im], 1)[20:25],  # collinear, in either order
        np.stack([im, ia, ib], 1)[25:],
        np.stack([ia, ia, ia], 1)[:3],  # points
    ]
    faces = np.concatenate([faces, *extra])
    t = rng.uniform(-0.2, 1.2, size=(30, 1))
    y = np.concatenate(
        [
            cloud_near(x, faces, rng, 100, spread=0.02),
            a + t * (b - a) + 0.01 * rng.normal(size=(30, 3)),
        ]
    )
    S = PointToSurface(faces, backend=backend)
    S.bind(y)
    x = x[S.nodes]  # some midpoints are left unused
    J, grad = S(x)
    assert np.isfinite(J) and np.isfinite(grad).all()
    d = S.closest(x).distance
    np.testing.assert_allclose(d, brute_distance(S.faces, x, y), atol=1e-12)
    assert (d[100:] <= np.linalg.norm(segment_closest(y[100:], a, b) - y[100:], axis=1) + 1e-12).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_points_on_slivers_are_on_the_surface(backend):
    """A sliver's interior is nearer than its edges: thin triangles must not be edges only."""
    rng = np.random.default_rng(13)
    x, faces = blob(subdivisions=2)
    i, j = faces[:40, 0], faces[:40, 1]
    tip = (x[i] + x[j]) / 2 + 1e-6 * np.linalg.norm(x[j] - x[i], axis=1)[:, None] * rng.normal(size=(40, 3))
    slivers = np.stack([i, len(x) + np.arange(40), j], 1)
    x = np.concatenate([x, tip])
    y = np.einsum("k,nki->ni", [0.3, 0.4, 0.3], x[slivers])
    S = PointToSurface(np.concatenate([faces, slivers]), backend=backend)
    S.bind(y)
    assert S.closest(x).distance.max() < 1e-9  # the edges are ~1e-7 away


@pytest.mark.parametrize("backend", BACKENDS)
def test_faces_of_a_larger_mesh_are_renumbered(backend):
    x, faces = blob(subdivisions=2)
    rng = np.random.default_rng(7)
    ids = rng.permutation(10 * len(x))[: len(x)]  # the surface's nodes inside a bigger mesh
    X = rng.normal(size=(10 * len(x), 3))
    X[ids] = x
    part = faces[: len(faces) // 2]  # a matching subset of the boundary
    S = PointToSurface(ids[part], backend=backend)
    assert (np.diff(S.nodes) > 0).all() and set(S.nodes) == set(ids[part].ravel())
    np.testing.assert_array_equal(S.nodes[S.faces], ids[part])
    y = cloud_near(x, part, rng, 100)
    S.bind(y)
    res = S.closest(X[S.nodes])
    np.testing.assert_allclose(res.distance, brute_distance(part, x, y), atol=1e-12)
    np.testing.assert_allclose(  # face and bary say where the closest point is
        np.einsum("mk,mki->mi", res.bary, X[ids[part][res.face]]), res.points, atol=1e-12
    )


LOSSES = [("squared", {}), ("huber", {"delta": 0.03}), ("trimmed", {"trim": 0.2})]


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("loss,options", LOSSES)
def test_gradient_matches_central_differences(backend, loss, options):
    rng = np.random.default_rng(8)
    x, faces = blob(subdivisions=2)
    S = PointToSurface(faces, loss=loss, backend=backend, **options)
    S.bind(cloud_near(x, faces, rng, 200))
    J, grad = S(x)
    assert grad.shape == x.shape and np.isfinite(grad).all()
    h = 1e-6
    for _ in range(4):  # random directions
        u = rng.normal(size=x.shape)
        fd = (S(x + h * u)[0] - S(x - h * u)[0]) / (2 * h)
        assert fd == pytest.approx(np.sum(grad * u), rel=1e-6, abs=1e-12)
    for i in np.flatnonzero(np.abs(grad).sum(1) > 0)[:5]:  # single coordinates
        e = np.zeros_like(x)
        e[i, 1] = h
        fd = (S(x + e)[0] - S(x - e)[0]) / (2 * h)
        assert fd == pytest.approx(grad[i, 1], rel=1e-5, abs=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_huber_is_squared_below_delta_and_linear_above(backend):
    rng = np.random.default_rng(9)
    x, faces = blob(subdivisions=2)
    y = cloud_near(x, faces, rng, 150)
    squared = PointToSurface(faces, backend=backend)
    squared.bind(y)
    d = squared.closest(x).distance
    huge = PointToSurface(faces, loss="huber", delta=1.01 * d.max(), backend=backend)
    huge.bind(y)
    (J0, g0), (J1, g1) = squared(x), huge(x)
    assert J1 == pytest.approx(J0, rel=1e-14)
    np.testing.assert_allclose(g1, g0, rtol=1e-14, atol=1e-18)

    delta = float(np.median(d))
    huber = PointToSurface(faces, loss="huber", delta=delta, backend=backend)
    huber.bind(y)
    rho = np.where(d <= delta, d**2, 2 * delta * d - delta**2)
    assert huber(x)[0] == pytest.approx(rho.mean() / 2, rel=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_trimmed_ignores_the_farthest_fraction(backend):
    rng = np.random.default_rng(10)
    x, faces = blob(subdivisions=2)
    y = cloud_near(x, faces, rng, 101)
    S = PointToSurface(faces, loss="trimmed", trim=0.1, backend=backend)
    S.bind(y)
    res = S.closest(x)
    np.testing.assert_allclose(res.sq_distances, res.distance**2)
    assert res.kept.sum() == 101 - 10
    d = np.sort(res.distance)
    assert res.distance[~res.kept].min() >= d[90]
    J, grad = S(x)
    assert J == pytest.approx(np.sum(d[:91] ** 2) / (2 * 91), rel=1e-12)

    y_far = y.copy()  # moving the ignored points farther changes nothing
    y_far[~res.kept] *= 3.0
    S.bind(y_far)
    J_far, grad_far = S(x)
    assert J_far == pytest.approx(J, rel=1e-12)
    np.testing.assert_allclose(grad_far, grad, rtol=1e-12, atol=1e-18)


def test_loss_param_names_either_parameter():
    _, faces = blob(subdivisions=1)
    assert PointToSurface(faces, loss="huber", loss_param=0.5).delta == 0.5
    assert PointToSurface(faces, loss="trimmed", loss_param=0.3).trim == 0.3
    assert PointToSurface(faces, loss="trimmed").trim == 0.1
    assert PointToSurface(faces, loss_param=0.3).loss == "squared"
    with pytest.raises(ValueError):
        PointToSurface(faces, loss="huber", loss_param=0.5, delta=0.5)


@pytest.mark.skipif(not numba_available(), reason="no numba")
def test_numba_and_numpy_agree():
    rng = np.random.default_rng(11)
    x, faces = blob()
    y = cloud_near(x, faces, rng, 400)
    out = []
    for backend in ("numpy", "numba"):
        S = PointToSurface(faces, loss="huber", delta=0.02, backend=backend)
        S.bind(y)
        out.append(S(x))
    assert out[0][0] == pytest.approx(out[1][0], rel=1e-12)
    np.testing.assert_allclose(out[0][1], out[1][1], rtol=1e-9, atol=1e-15)


def test_bad_inputs_are_refused():
    x, faces = blob(subdivisions=1)
    S = PointToSurface(faces)
    with pytest.raises(RuntimeError):
        S(x)
    for bad in (
        np.full((5, 3), np.nan),
        np.array([[0.0, 0.0, np.inf]]),
        np.zeros((5, 2)),
        np.zeros((0, 3)),
        np.zeros(3),
    ):
        with pytest.raises(ValueError):
            S.bind(bad)
    S.bind(np.ones((4, 3)))
    with pytest.raises(ValueError):
        S(x[:-1])
    x_nan = x.copy()
    x_nan[3, 1] = np.nan
    with pytest.raises(ValueError):
        S(x_nan)  # before any index
    S(x)
    with pytest.raises(ValueError):
        S(x_nan)  # with one
    for kwargs in (
        {"loss": "cauchy"},
        {"loss": "huber"},
        {"loss": "huber", "delta": -1.0},
        {"loss": "trimmed", "trim": 1.0},
        {"margin": 0.0},
        {"backend": "cuda"},
    ):
        with pytest.raises(ValueError):
            PointToSurface(faces, **kwargs)
    for bad_faces in (
        np.zeros((0, 3), int),
        np.zeros((4, 4), int),
        -np.ones((2, 3), int),
        faces + 0.5,
    ):
        with pytest.raises(ValueError):
            PointToSurface(bad_faces)


@needs_liver()
def test_liver_cloud_against_brute_force():
    meshio = pytest.importorskip("meshio")
    from service.mesh import TetMesh

    mesh = meshio.read(LIVER / "liver.msh")
    matching = np.load(LIVER / "matching-triangles.npy")
    faces = np.asarray(TetMesh(mesh.points, mesh.cells_dict["tetra"]).surface_faces)
    seq = LIVER / "sequences/neohookean/s1"
    positions = np.load(seq / "positions-default.npy", mmap_mode="r")
    y = np.loadtxt(seq / "pointclouds/pc10.txt")[::5]
    for tris in (matching, faces):
        S = PointToSurface(tris)
        S.bind(y)
        local = np.searchsorted(S.nodes, tris)
        for frame in (0, 9, 10):
            x = np.asarray(positions[frame])[S.nodes]
            np.testing.assert_allclose(S.closest(x).distance, brute_distance(local, x, y), atol=1e-12)
    assert S.closest(np.asarray(positions[10])[S.nodes]).rms < 1e-9  # the cloud lies on it


def test_bind_accepts_a_read_only_cloud():
    """A MessagePack packed array arrives as a read-only np.frombuffer view."""
    import trimesh

    from service.registration.distance import PointToSurface

    sphere = trimesh.creation.icosphere(subdivisions=2)
    dist = PointToSurface(np.asarray(sphere.faces))
    pts = np.frombuffer((np.asarray(sphere.vertices[:20]) * 1.5).tobytes(), dtype=np.float64).reshape(20, 3)
    assert not pts.flags.writeable
    dist.bind(pts)
    J, grad = dist(np.asarray(sphere.vertices)[dist.nodes])
    assert np.isfinite(J) and J > 0 and np.isfinite(grad).all()


@pytest.mark.skipif(not numba_available(), reason="no numba")
def test_hinted_builds_give_the_same_lists():
    """A build seeded with each point's last closest face (or a wrong one) lists exactly the
    triangles an unseeded build lists, in the same order, short lists and long ones."""
    rng = np.random.default_rng(21)
    x, faces = blob(subdivisions=2)
    S = PointToSurface(faces, backend="numba")
    S.bind(cloud_near(x, faces, rng, 80))
    S(x)
    h = S.candidates._spaces[0]
    K = S._kernels
    moved = x + 0.02 * rng.normal(size=x.shape)
    K.refit(moved, S.faces, h.order, h.span, h.box, h.tri)
    m = len(S.points)
    for reach in (0.0, 0.1, 1.0):
        lists = []
        for hint in (np.empty(0, np.intp), S._hint, rng.integers(len(faces), size=m).astype(np.intp)):
            face, start = np.empty(len(faces) * m, np.intp), np.empty(m + 1, np.intp)
            n = K.candidates(moved, S.faces, h.order, h.span, h.box, h.tri, S.points, reach, hint, h.leaf, face, start)
            assert n > 0
            lists.append((face[:n].copy(), start.copy()))
        assert reach < 1.0 or np.diff(lists[0][1]).max() > 32  # long lists' order is tested too
        for face, start in lists[1:]:
            np.testing.assert_array_equal(face, lists[0][0])
            np.testing.assert_array_equal(start, lists[0][1])


@pytest.mark.parametrize("backend", BACKENDS)
def test_last_match_is_the_last_evaluation(backend):
    """After an evaluation, last_match holds its positions, faces, weights and residuals (what
    closest() reports) and each point's weight in the gradient; a new cloud clears it."""
    rng = np.random.default_rng(22)
    x, faces = blob(subdivisions=2)
    S = PointToSurface(faces, backend=backend, loss="trimmed", trim=0.2)
    S.bind(cloud_near(x, faces, rng, 50))
    assert S.last_match is None
    S(x)
    match, c = S.last_match, S.closest(x)
    np.testing.assert_array_equal(match.face, c.face)
    np.testing.assert_allclose(match.W.T, c.bary, atol=1e-14)
    np.testing.assert_allclose(match.r.T, c.points - S.points, atol=1e-14)
    np.testing.assert_allclose(match.weight, c.kept / c.kept.sum())
    S.bind(cloud_near(x, faces, rng, 50))
    assert S.last_match is None

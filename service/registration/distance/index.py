"""The distance's candidate index: which triangles each point must look at, and when to rebuild.

A build at positions x0 gives each point every triangle within its distance plus twice a margin
M; while no vertex has moved more than M from x0 the closest triangle is among them, so an
evaluation looks at a few triangles per point, not all (the proof, and how a build finds them:
docs/distance.md). The compiled backend finds them in a bounding-volume hierarchy kept across
frames and refitted at every build; the NumPy backend in a k-d tree over the centroids.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging

import numpy as np
from scipy.spatial import cKDTree

from .geometry import _mean_edge, _norm2, closest_point_on_triangles
from .kernels import _TRI

log = logging.getLogger(__name__)

Array = np.ndarray

#: Triangles per leaf of the compiled backend's hierarchy (about: leaves hold f / 2^depth).
_LEAF = 8
#: A spatial structure is laid out again once a vertex has moved this many mean edges from
#: where it was laid out. Only speed depends on it: the hierarchy's boxes are refitted, exact,
#: at every build, and the centroid tree's search is widened by the motion.
_RELAYOUT_HIERARCHY = 8.0
_RELAYOUT_TREE = 0.5


class NonFinitePositions(ValueError):
    """The surface's positions hold NaN or infinite values: the forward model's answer, never
    the client's cloud (checked on arrival), so the engine reports the frame non_finite."""


@dataclasses.dataclass(frozen=True)
class Index:
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
class Hierarchy:
    """A bounding-volume hierarchy over the triangles, for the compiled backend.

    Its topology (``order``, ``span``: see :func:`bvh_layout`) is chosen once at positions x0
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
class CentreTree:
    """A k-d tree over the triangles' centroids at positions x0, for the numpy backend.

    Kept while the surface moves less than a tolerance from x0: every distance it returns is
    then wrong by at most that motion, which the search widens by (docs/distance.md).
    """

    x0: Array  # (p, 3) positions at the build
    edge: float  # mean edge length there
    tree: cKDTree  # over the centroids g_t(x0)
    g: Array  # (3, f) the centroids g_t(x0), coordinates first
    radius: Array  # (f,) r_t = max_k |v_k(x0) - g_t(x0)|, each triangle's bounding radius


class Candidates:
    """The candidate triangles of each point of a cloud, in indices exact while the surface moves
    less than their margin: built, kept for the frame's returns, and looked up.

    Shape: faces (f, 3) renumbered into 0..p-1, columns their transpose (3, f); every ``x`` is
    (p, 3). ``kernels`` are the compiled kernels, or None for the NumPy backend. Why a
    candidate list is exact, and how a build finds one: docs/distance.md.
    """

    def __init__(
        self,
        faces: Array,
        columns: Array,
        kernels,
        *,
        margin: float | None,
        margin_factor: float,
        keep: int,
        lone: bool = False,
    ) -> None:
        self.faces, self._columns, self._kernels = faces, columns, kernels
        self.lone = lone  # every evaluation the only one of its cloud: one-offs only
        self.n_nodes = int(faces.max()) + 1
        self.margin, self.margin_factor, self.keep = margin, margin_factor, keep
        self.points: Array | None = None
        self._yt: Array | None = None
        self.n_builds = 0  # candidate indices built (at least one per frame)
        self.n_one_off = 0  # ... of which one-offs (margin 0, see lookup)
        self.n_layouts = 0  # spatial structures (hierarchy or centroid tree) built
        self._indices: list[Index] = []  # this frame's, the last used first
        self._footprints: list[tuple[Array, bool]] = []  # x0 of recent indices, with a margin?
        self._spaces: list[Hierarchy | CentreTree] = []  # kept across frames, last used first
        self._capacity = 0  # pairs the compiled build's buffer holds

    @property
    def current(self) -> Index | None:
        """The index of the last evaluation (None before the first one of a frame)."""
        return self._indices[0] if self._indices else None

    def bind(self, points: Array, yt: Array) -> None:
        """A new frame's cloud (m, 3), and the same coordinates first (3, m): this frame's
        indices go; the footprints of those with a margin stay (a frame starts where the last
        one ended)."""
        self.points, self._yt = points, yt
        self._indices = []
        self._footprints = [(x0, full) for x0, full in self._footprints if full]

    def lookup(self, x: Array, hint: Array) -> Index:
        """An index exact at x: the last used one still within its margin of x, else a new one.

        Line searches probe a point and come back: the ``keep`` indices of this frame last used
        are tried in that order, so coming back costs a motion check (a few microseconds), not
        a build. Any of them is exact at x by the margin argument (docs/distance.md),
        whatever positions were evaluated in between. A new index gets the margin M only where
        the surface dwells (see :meth:`_dwells`); elsewhere, it is a one-off: margin 0, exact
        at x alone (and so reused only at the same x, e.g. by ``closest`` after a call), about
        a third of the cost since each point then looks no farther than its closest triangle.
        """
        for i, ix in enumerate(self._indices):
            moved = self.motion(x, ix.x0)
            if not np.isfinite(moved):
                raise NonFinitePositions("x contains NaN or infinite coordinates")
            if moved <= ix.margin * ix.margin:
                if i:
                    self._indices.insert(0, self._indices.pop(i))
                return ix
        if not self._indices and not np.isfinite(x).all():
            raise NonFinitePositions("x contains NaN or infinite coordinates")
        space = self._space_at(x)
        M = self._margin(space.edge, x)
        ix = self._build(x, space, M if self._dwells(x, M) else 0.0, hint)
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
        if self.lone:
            return False
        if not self._footprints:  # the first evaluation of a session: nothing known yet
            return True
        return any(self.motion(x, x0) <= M * M for x0, _ in self._footprints)

    def motion(self, x: Array, x0: Array) -> float:
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

    def _space_at(self, x: Array) -> Hierarchy | CentreTree:
        """A spatial structure laid out near x: a kept one, else a new one laid out at x.

        Two are kept, so that evaluations alternating between two far places (the engine's
        rest state and the current frame) do not lay one out each time.
        """
        tolerance = _RELAYOUT_TREE if self._kernels is None else _RELAYOUT_HIERARCHY
        for i, space in enumerate(self._spaces):
            if self.motion(x, space.x0) <= (tolerance * space.edge) ** 2:
                if i:
                    self._spaces.insert(0, self._spaces.pop(i))
                return space
        space = self._centre_tree(x) if self._kernels is None else self._hierarchy(x)
        self._spaces = [space, *self._spaces[:1]]
        return space

    def _build(self, x: Array, space: Hierarchy | CentreTree, M: float, hint: Array) -> Index:
        """Candidate pairs at positions x: every triangle within d0 + 2 M of each point."""
        if self._kernels is not None:
            face, start = self._candidates_compiled(x, space, M, hint)
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
            return Index(
                x0=x.copy(), margin=M, face=face, start=start, tri=tri, active=active, nodes=self._nodes_of(active)
            )
        count = np.diff(start)
        rows = np.repeat(np.arange(m), count)
        width = int(count.max())
        used = np.zeros(len(self.faces), np.intp)
        used[face] = 1
        tri = np.cumsum(used).take(face) - 1  # position of each pair's face among the used
        used = np.flatnonzero(used)
        full = bool((count == width).all())
        return Index(
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

    def _candidates_compiled(self, x: Array, h: Hierarchy, M: float, hint: Array) -> tuple[Array, Array]:
        """Face (P,) and start (m + 1,) of a build, from the hierarchy refitted at x."""
        K = self._kernels
        K.refit(x, self.faces, h.order, h.span, h.box, h.tri)
        m = len(self.points)
        start = np.empty(m + 1, np.intp)
        self._capacity = max(self._capacity, 16 * m)
        while True:
            face = np.empty(self._capacity, np.intp)
            n = K.candidates(
                x, self.faces, h.order, h.span, h.box, h.tri, self.points, 2 * M, hint,
                h.leaf, face, start,
            )  # fmt: skip
            if n >= 0:
                return face[:n], start
            self._capacity *= 4

    def _hierarchy(self, x: Array) -> Hierarchy:
        """A new hierarchy laid out at positions x (see :func:`bvh_layout`)."""
        A, B, C = (x.take(self._columns[k], axis=0) for k in range(3))  # (f, 3) each
        order, span = bvh_layout((A + B + C) / 3.0, _LEAF)
        f = len(self.faces)
        leaves = np.arange((len(span) - 1) // 2, len(span))  # their spans tile order, in order
        leaf = np.empty(f, np.intp)
        leaf[order] = np.repeat(leaves, span[leaves, 1] - span[leaves, 0])
        self.n_layouts += 1
        return Hierarchy(
            x0=x.copy(),
            edge=_mean_edge(A, B, C),
            order=order,
            span=span,
            box=np.empty((len(span), 6)),
            tri=np.empty((f, _TRI)),
            leaf=leaf,
        )

    def _candidates_numpy(self, x: Array, tree: CentreTree, M: float) -> tuple[Array, Array]:
        """Face (P,) and start (m + 1,) of a build, from the centroid tree (laid out near x)."""
        yt = self._yt
        m = yt.shape[1]
        delta = np.sqrt(self.motion(x, tree.x0))

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
        start = np.searchsorted(rows, np.arange(m + 1))  # no empty list: see docs/distance.md
        d = np.sqrt(self._pair_sq(x, start, face))
        d0 = np.minimum.reduceat(d, start[:-1])
        keep = d <= (d0 + 2 * M + 1e-9 * (M + d0)).take(rows)
        rows, face = rows[keep], face[keep]
        return face, np.searchsorted(rows, np.arange(m + 1))

    def _centre_tree(self, x: Array) -> CentreTree:
        """A k-d tree over the centroids at positions x, with each triangle's bounding radius."""
        xt = np.ascontiguousarray(x.T)
        A, B, C = (xt.take(self._columns[k], axis=1) for k in range(3))  # (3, f) each
        g = (A + B + C) / 3.0
        radius = np.sqrt(np.maximum(np.maximum(_norm2(A - g), _norm2(B - g)), _norm2(C - g)))
        self.n_layouts += 1
        return CentreTree(
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


def bvh_layout(g: Array, leaf: int) -> tuple[Array, Array]:
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

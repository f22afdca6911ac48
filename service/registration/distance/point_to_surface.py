"""The point-to-surface distance of a cloud: J(x), its gradient, and where each point meets.

:class:`PointToSurface` evaluates the registration's objective tens of times per frame; each
evaluation looks only at each point's candidate triangles (:mod:`.index`), exact per pair
(:mod:`.geometry` in NumPy, :mod:`.kernels` compiled).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

import numpy as np

from ...jit import available
from ..settings import Loss
from .geometry import _TINY, _is_thin, _unit_clamp, _weights
from .index import Candidates, Index
from .kernels import _ROW, compiled

Array = np.ndarray
Backend = Literal["auto", "numba", "numpy"]
_NO_HINT = np.empty(0, np.intp)


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
    reuse, so that a line search that probes far and comes back does not rebuild. ``lone``: each
    cloud is evaluated once (the engine's rest state), so every index is a one-off.
    ``backend`` is ``"numba"`` (the compiled kernels), ``"numpy"`` (the vectorised reference)
    or ``"auto"`` (numba when it imports). ``n_builds`` counts the indices built (at least one
    per frame, more when the surface moves beyond the margin), ``n_one_off`` those of them
    built for a lone evaluation (margin 0, see ``Candidates.lookup``), ``n_layouts`` the spatial
    structures laid out (rarely: they are kept across frames). All three only ever grow.

    >>> import trimesh
    >>> sphere = trimesh.creation.icosphere(subdivisions=2)
    >>> S = PointToSurface(sphere.faces, backend="numpy")
    >>> S.bind(2.0 * sphere.vertices[:10])  # each point 1 away from the surface
    >>> J, grad = S(sphere.vertices[S.nodes])
    >>> round(2 * J, 12), grad.shape
    (1.0, (162, 3))

    Why the candidate index is exact, how a build finds the candidates, and how an evaluation
    skips most of them: docs/distance.md (the index itself: :mod:`.index`).
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
        lone: bool = False,
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
        if loss == "huber" and not (delta is not None and 0 < delta <= 1e6):  # its square must be finite
            raise ValueError(f"the huber loss needs a positive threshold delta (a length), at most 1e6, got {delta}")
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
            backend = "numba" if available() else "numpy"
        self._kernels = compiled() if backend == "numba" else None
        if backend == "numba" and self._kernels is None:
            raise ImportError("backend 'numba' asked for, but numba does not import")
        self.backend = backend
        self.nodes, local = np.unique(faces, return_inverse=True)
        self.faces = np.ascontiguousarray(local.reshape(faces.shape), dtype=np.intp)
        self._columns = np.ascontiguousarray(self.faces.T)  # (3, f): contiguous for take
        self.loss, self.delta, self.trim = loss, delta, trim
        self.margin, self.margin_factor = margin, margin_factor
        self.points: Array | None = None
        self._yt: Array | None = None  # the points, coordinates first (3, m)
        self.keep = int(keep)
        self.candidates = Candidates(
            self.faces,
            self._columns,
            self._kernels,
            margin=margin,
            margin_factor=margin_factor,
            keep=self.keep,
            lone=lone,
        )
        self._last: tuple | None = None  # the last evaluation's match, as last_match gives it
        self._uniform: Array | None = None  # the points' one weight (squared loss), per cloud
        self._hint = _NO_HINT  # each point's last closest face this frame (compiled builds)

    @property
    def _index(self) -> Index | None:
        """The index of the last evaluation (None before the first one of a frame)."""
        return self.candidates.current

    @property
    def n_builds(self) -> int:
        """Candidate indices built: at least one per frame, more when the surface moves beyond
        the margin."""
        return self.candidates.n_builds

    @property
    def n_one_off(self) -> int:
        """Indices built for a lone evaluation (margin 0; see :meth:`.index.Candidates.lookup`)."""
        return self.candidates.n_one_off

    @property
    def n_layouts(self) -> int:
        """Spatial structures laid out (rarely: they are kept across frames)."""
        return self.candidates.n_layouts

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
        self.candidates.bind(self.points, self._yt)
        self._last = self._uniform = None
        self._hint = _NO_HINT

    @property
    def far_share(self) -> bool:
        """Whether J carries a share its forces barely move: huber's far points each add
        delta (d - delta / 2), which grows with their distance while their pull stays delta."""
        return self.loss == "huber"

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
        of this frame still exact at x, or builds one (see :meth:`.index.Candidates.lookup`). The residual is
        formed from the vertices, not from dot products.
        """
        ix = self.candidates.lookup(x, self._hint)
        m = len(self.points)
        W, r = np.empty((3, m)), np.empty((3, m))
        if self._kernels is not None:
            face = np.empty(m, np.intp)
            T = np.empty((ix.active.size, _ROW))
            self._kernels.nearest(x, self.faces, ix.active, ix.tri, ix.start, self.points, T, face, W, r)
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

    def _nearest_numpy(self, x: Array, ix: Index) -> tuple[Array, Array, Array]:
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

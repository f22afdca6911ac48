"""The Levenberg-Marquardt step for registration with a low-rank forward model.

Registration is nonlinear least squares: Phi(g) = sum_j w_j d_j(u_g)^2 / 2 + alpha/2 |g|^2
(w_j = 1/m for the squared loss). For the reduced surrogate, u = U c(g) with U the basis
readout (3p, r) and C = dc/dg (r, K) cheap to form in product form at any g
(:class:`~service.surrogate.jacobian.CoefficientJacobian`), so the Gauss-Newton Hessian at g is

    H = C^T A C + alpha I,   A = N^T diag(w) N  (r, r),   N_j = d(d_j)/dc = sum_v b_jv n_j^T U_v,

with n_j the unit vector from point j to its closest point (its face's normal where the point
lies on the surface) and b_jv its barycentric weights. A damped step (H + mu I) d = -grad
needs no K x K algebra: with z = C d, (lam I + C C^T A) z = C v and d = (v - C^T A z) / lam,
lam = alpha + mu, v = -grad, an r x r solve (the beam: K = 939 forces, r = 64). The FEM
gives du/dg itself (``DenseJacobian`` in ``fem/jacobian.py``: U = du/dg, C = I, r = K), which pays where the
support is small (the paper's liver: 60 nodes, 180 solves with the Newton factorisation). Once
it has formed one, its later steps go through products with du/dg instead (a solve each),
preconditioned by the one it holds (:class:`KrylovGaussNewton`): a few solves a step.

Why this, not L-BFGS-B, for whole-surface cold starts: L-BFGS-B learns the curvature from
gradients, about one direction per iteration, and the rest Jacobian that preconditions it
misleads as the shape moves; Gauss-Newton re-linearises at every accepted step. Measured on the
beam (60 cases from rest, gtol 1e-3, means): 4.9 iterations and 5.9 evaluations against 18.0 and
20.3, TRE 0.079 against 0.120 mm. It does not take bounds, and it needs the model's Jacobian, so
L-BFGS-B stays the default (and the paper's method).
"""

from __future__ import annotations

import functools

import numpy as np
import scipy.sparse as sp
from scipy.linalg import cho_factor, cho_solve
from scipy.linalg.lapack import dgesv

from ..jit import kernels
from .distance import Match
from .precondition import residual_matrix, residual_rows

Array = np.ndarray


class GaussNewtonModel:
    """The damped Gauss-Newton model of Phi at one accepted point.

    `jac` offers U (3p, r), gram_product(A) = C C^T A for a symmetric A (r, r), Fortran-ordered,
    matvec (C v) and rmatvec (C^T w), and may offer gradient_image(alpha): C grad for the
    gradient the operator's last evaluation gave at jac's point (None if it does not know it);
    `match` is the distance's at this point, `faces` (f, 3) the distance's local faces; grad
    (K,) the exact gradient there (the step's right-hand side: the model's Hessian only
    approximates), the one the operator's last evaluation gave if it was at this point.
    """

    def __init__(self, jac, match: Match, faces: Array, grad: Array, alpha: float, A: Array | None = None) -> None:
        if A is None:  # else distance_gram(jac.U, match, faces)[1], made beside the Jacobian
            _, A = distance_gram(jac.U, match, faces)
        self.CCA = jac.gram_product(A)  # (r, r), Fortran-ordered as LAPACK takes it
        self.A = A
        self.jac = jac
        self.v = -np.asarray(grad, np.float64).ravel()
        image = getattr(jac, "gradient_image", None)  # C grad without a product over K
        Cgrad = image(alpha) if image is not None else None
        self.Cv = jac.matvec(self.v) if Cgrad is None else -Cgrad
        self.alpha = float(alpha)
        self._diagonal = slice(None, None, len(A) + 1)  # of a flattened (r, r)
        trace = float(self.CCA.T.ravel()[self._diagonal].sum())
        self.scale = max(trace / len(A), 0.0)  # the mean curvature the model sees

    def step(self, mu: float) -> Array:
        """d with (C^T A C + (alpha + mu) I) d = -grad. Shape: (K,)."""
        lam = self.alpha + mu
        M = self.CCA.copy(order="F")
        M.T.ravel()[self._diagonal] += lam  # a view: M.T is C-ordered
        _, _, z, info = dgesv(M, self.Cv, overwrite_a=1)  # LAPACK directly, in place: a
        if info != 0:  # third of np.linalg.solve's time at r = 64; singular only at lam = 0
            raise np.linalg.LinAlgError("singular Levenberg-Marquardt system")
        return (self.v - self.jac.rmatvec(self.A @ z)) / lam

    def predicted(self, d: Array, mu: float) -> float:
        """The model's decrease for step d taken with damping mu: d^T (mu d - grad) / 2."""
        return 0.5 * float(d @ (mu * d + self.v))


#: The conjugate-gradient step's relative residual: an inexact Newton method's forcing term;
#: the step's last percent costs more solves than the iteration it could save
KRYLOV_RTOL = 1e-2
#: Conjugate-gradient iterations (two solves each) before the held Jacobian counts as too far
#: from this g to precondition: 20 solves, a fifth of what forming the paper's liver's 180
#: columns costs its caller; the step is then taken through the Jacobian formed in full
KRYLOV_MAX_ITER = 10


class KrylovGaussNewton:
    """The damped Gauss-Newton model of Phi at one accepted point, through products with the
    exact Jacobian J (``fem/jacobian.py``'s JacobianProducts: a solve each) instead of J itself.

    The step solves (J^T A J + (alpha + mu) I) d = -grad by conjugate gradients, preconditioned
    with the same matrix made from the held Jacobian J_h (formed in full at an earlier g) and
    this point's match: where the shape moved little since J_h, a few iterations (two solves
    each) replace 3k solves. Where they do not suffice (KRYLOV_MAX_ITER), step() gives None and
    the caller forms J. The gradient stays exact, so only the step, not the answer, is inexact.
    """

    def __init__(self, products, match: Match, faces: Array, grad: Array, alpha: float) -> None:
        self.products = products
        self.N = weighted_matrix(match, faces, products.n_rows)
        # the held Jacobian is the FEM's DenseJacobian (C = I): its model's matrix is A itself
        _, self.A_held = distance_gram(products.held.U, match, faces)
        self.v = -np.asarray(grad, np.float64).ravel()
        self.alpha = float(alpha)
        self.scale = max(float(np.trace(self.A_held)) / len(self.A_held), 0.0)
        self.iterations = 0  # conjugate-gradient iterations of the last step
        self._residual: tuple[Array, Array] | None = None  # (d, v - (H + mu I) d) of the last step

    def _curvature(self, x: Array, lam: float) -> Array:
        """(J^T A J + lam I) x: two solves."""
        p = self.products
        return p.rmatvec(self.N.T @ (self.N @ p.matvec(x))) + lam * x

    def step(self, mu: float) -> Array | None:
        """d with (J^T A J + (alpha + mu) I) d = -grad to KRYLOV_RTOL, or None. Shape: (K,)."""
        if not self.products.ready():  # the factor there no longer holds (an unstable state)
            return None
        lam = self.alpha + mu
        M = self.A_held.copy()
        M.ravel()[:: len(M) + 1] += lam
        try:
            factor = cho_factor(M, lower=True, overwrite_a=True, check_finite=False)
        except np.linalg.LinAlgError:  # lam = 0 on a singular model: the caller forms J
            return None
        d, r = np.zeros_like(self.v), self.v.copy()
        z = cho_solve(factor, r, check_finite=False)
        p, rz, goal = z.copy(), float(r @ z), KRYLOV_RTOL * float(np.linalg.norm(self.v))
        for it in range(1, KRYLOV_MAX_ITER + 1):
            Hp = self._curvature(p, lam)
            pHp = float(p @ Hp)
            if not pHp > 0.0:  # H is positive definite: only rounding gets here
                return None
            step = rz / pHp
            d += step * p
            r -= step * Hp
            self.iterations = it
            if np.linalg.norm(r) <= goal:
                self._residual = (d, r)
                return d
            z = cho_solve(factor, r, check_finite=False)
            rz, rz_old = float(r @ z), rz
            p = z + (rz / rz_old) * p
        return None

    def predicted(self, d: Array, mu: float) -> float:
        """The model's decrease for the step d of the last step(mu): v.d - d.H d / 2, with H d
        read off the step's residual r = v - (H + mu I) d, no solve."""
        if self._residual is None or self._residual[0] is not d:
            raise ValueError("predicted() takes the last step()'s own d")
        r = self._residual[1]
        return 0.5 * float(d @ (self.v + mu * d + r))


def distance_gram(U: Array, match: Match, faces: Array) -> tuple[Array, Array]:
    """The rows sqrt(w_j) N_j (m, r), in U's dtype, and A = N^T diag(w) N (r, r), float64:
    the distance's curvature seen through U (the Gauss-Newton model's, the noise term's)."""
    Nw = weighted_rows(U, match, faces)
    return Nw, (Nw.T @ Nw).astype(np.float64, copy=False)


def weighted_rows(U: Array, match: Match, faces: Array) -> Array:
    """sqrt(w_j) N_j for every point (see the module docstring), U's dtype. Shape: U (3p, r) ->
    (m, r). One compiled pass where numba imports (about 75 us on the beam's 500 points, against
    about 350 us for the same in NumPy calls), else NumPy."""
    K = _compiled()
    kernel = None if K is None else K._rows_loop
    m, r = match.face.size, U.shape[1]
    if kernel is not None:
        out = np.empty((m, r), U.dtype)
        kernel(np.ascontiguousarray(U), match.x, faces, match.face, match.W, match.r,
               np.ascontiguousarray(match.weight, np.float64), out)  # fmt: skip
        return out
    N = residual_rows(U, faces[match.face], match.W.T, _directions(match, faces))
    return N * np.sqrt(match.weight)[:, None].astype(N.dtype)


def weighted_matrix(match: Match, faces: Array, n_rows: int) -> sp.csr_matrix:
    """weighted_rows' rows over the nodes' displacement itself (U the identity), sparse: nine
    entries a point. Shape: (m, n_rows = 3p), float64."""
    weighted = match.W.T * np.sqrt(match.weight)[:, None]  # each point's weight in its barycentric ones
    return residual_matrix(faces[match.face], weighted, _directions(match, faces), n_rows)


def _directions(match: Match, faces: Array) -> Array:
    """Each point's unit direction: to its closest point, or its face's normal where it lies
    on the surface. Shape: (m, 3)."""
    tri = match.x[faces[match.face]]  # (m, 3 vertices, 3)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    res = match.r.T  # (m, 3)
    d = np.linalg.norm(res, axis=1)
    off = d > _ON_SURFACE * (float(np.abs(match.x).max()) or 1.0)
    n[off] = res[off] / d[off, None]
    return n


#: A point nearer its closest point than this (relative to the coordinates' size) lies on the
#: surface: its direction is its face's normal, not the (noisy) residual's.
_ON_SURFACE = 1e-9


def _rows_loop(U, x, faces, face, W, r, weight, out):
    """weighted_rows' loop: the direction of each point, then nine rows of U."""
    size = 0.0
    for i in range(x.shape[0]):
        for a in range(3):
            size = max(size, abs(x[i, a]))
    tol = _ON_SURFACE * (size if size > 0 else 1.0)
    k_r = U.shape[1]
    for j in range(face.size):
        f = face[j]
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        rx, ry, rz = r[0, j], r[1, j], r[2, j]
        d = np.sqrt(rx * rx + ry * ry + rz * rz)
        if d > tol:
            nx, ny, nz = rx / d, ry / d, rz / d
        else:  # on the surface: the face's normal
            ax, ay, az = x[i1, 0] - x[i0, 0], x[i1, 1] - x[i0, 1], x[i1, 2] - x[i0, 2]
            bx, by, bz = x[i2, 0] - x[i0, 0], x[i2, 1] - x[i0, 1], x[i2, 2] - x[i0, 2]
            nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
            s = np.sqrt(nx * nx + ny * ny + nz * nz)
            s = 1.0 / s if s > 0 else 0.0
            nx, ny, nz = nx * s, ny * s, nz * s
        root = np.sqrt(weight[j])
        t = U.dtype.type
        w0, w1, w2 = root * W[0, j], root * W[1, j], root * W[2, j]
        c00, c01, c02 = t(w0 * nx), t(w0 * ny), t(w0 * nz)
        c10, c11, c12 = t(w1 * nx), t(w1 * ny), t(w1 * nz)
        c20, c21, c22 = t(w2 * nx), t(w2 * ny), t(w2 * nz)
        r0, r1, r2 = 3 * i0, 3 * i1, 3 * i2
        for k in range(k_r):  # each entry written once, its nine terms summed in one order
            out[j, k] = (
                c00 * U[r0, k]
                + c01 * U[r0 + 1, k]
                + c02 * U[r0 + 2, k]
                + c10 * U[r1, k]
                + c11 * U[r1 + 1, k]
                + c12 * U[r1 + 2, k]
                + c20 * U[r2, k]
                + c21 * U[r2 + 1, k]
                + c22 * U[r2 + 2, k]
            )


_compiled = kernels(_rows_loop)  # the loop compiled (numba), or None


@functools.cache
def prepare() -> None:
    """Compile (or load from numba's disk cache) the rows kernel for both Jacobians' dtypes
    (the network's float32, the FEM's float64), once per process: a session using
    Levenberg-Marquardt calls this when it opens, so its first frame does not pay 0.3 s (a
    cached compile) to seconds (a fresh one) inside its time budget."""
    x = np.zeros((3, 3))
    match = Match(x, np.zeros(1, np.intp), np.full((3, 1), 1.0 / 3.0), np.ones((3, 1)), np.ones(1))
    faces = np.array([[0, 1, 2]], np.intp)
    for dtype in (np.float32, np.float64):
        weighted_rows(np.zeros((9, 1), dtype), match, faces)

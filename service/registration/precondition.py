"""Preconditioners for the registration problem: a Gauss-Newton model at the frame's start, and
the curvature a stream carries from frame to frame.

Registration is a nonlinear least-squares problem: with r_j the signed point-to-plane residual
of point j (normal of its closest triangle), the Hessian of Phi(g) = J + alpha/2 |g|^2 is close
to  H = (1/m) A^T A + alpha I,  A_j = dr_j/dg = sum_v w_jv n_j^T B_v,  where B = du/dg is the
forward model's Jacobian (rows of the nodes of the closest triangles, barycentric weights w).
Forces on neighbouring nodes move the surface almost alike, so H is badly conditioned and plain
L-BFGS needs many iterations; in variables z with H = L L^T, g = L^-T z, the curvature is about
the identity.

The model's Jacobian at rest is low-rank: the network answers in r basis coefficients, and the
FEM's rest compliance has a fast-decaying spectrum (truncated SVD), so B = U Q^T with U (3p, r)
and Q (K, r) orthonormal, and H = Q S Q^T + alpha (I - Q Q^T) with an
r x r matrix S. The factor L is then cheap (an r x r Cholesky) and applying it costs two (K, r)
products. An approximation is all a preconditioner needs (the optimisation itself uses exact
gradients), but the rest Jacobian misleads once the shape is far from rest, so the model is
damped in both parts, Levenberg-Marquardt style (measured on the beam from rest: a third of
L-BFGS-B's iterations for the network, and the Newton method's TRE from 4.4 to 0.11 mm; on the
liver's partial clouds it does not help the network, so it is opt-in).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy.linalg.blas import dger, dtrsv

from ..jit import kernels

Array = np.ndarray


def residual_rows(U: Array, faces: Array, bary: Array, normals: Array) -> Array:
    """N = d(point-to-plane residual)/d(coefficients): N_j = sum_v w_jv n_j^T U_v, nine of U's
    rows per point.

    Shape: U (3p, r) node-major displacement of the matching nodes per coefficient; faces
    (m, 3) local node ids of each point's closest triangle; bary (m, 3); normals (m, 3) ->
    (m, r), U's dtype. Compiled where numba imports (65 us on the beam's 500 points against
    260 us for a sparse product, whose construction dominates), else that product.
    """
    m = len(faces)
    K = _compiled()
    kernel = None if K is None else K._rows_loop
    if kernel is not None:
        out = np.empty((m, U.shape[1]), U.dtype)
        kernel(np.ascontiguousarray(U), np.ascontiguousarray(faces, np.intp),
               np.ascontiguousarray(bary, np.float64), np.ascontiguousarray(normals, np.float64), out)  # fmt: skip
        return out
    return np.asarray(residual_matrix(faces, bary, normals, U.shape[0]).astype(U.dtype) @ U)


def residual_matrix(faces: Array, bary: Array, normals: Array, n_rows: int) -> sp.csr_matrix:
    """residual_rows' N as a sparse matrix over the nodes' displacement, nine entries a point.
    Shape: faces (m, 3), bary (m, 3), normals (m, 3) -> (m, n_rows = 3p), float64."""
    m = len(faces)
    coef = (bary[:, :, None] * normals[:, None, :]).ravel()
    cols = (3 * faces[:, :, None] + np.arange(3)).ravel()
    return sp.csr_matrix((coef, cols, np.arange(0, 9 * m + 1, 9)), shape=(m, n_rows))


def _rows_loop(U, faces, bary, normals, out):
    """residual_rows' loop: out[j] = sum over vertex v, axis a of bary * normal * U's row."""
    r = U.shape[1]
    for j in range(faces.shape[0]):
        for k in range(r):
            out[j, k] = 0.0
        for v in range(3):
            for a in range(3):
                c = U.dtype.type(bary[j, v] * normals[j, a])
                row = 3 * faces[j, v] + a
                for k in range(r):  # an explicit loop: a slice here allocates per pass
                    out[j, k] += c * U[row, k]


_compiled = kernels(_rows_loop)  # the loop compiled (numba), or None


class _Whitened:
    """g = c L^-T z for some factor H = L L^T (the subclass's `whiten` applies L^-1); c makes
    the first (quasi-)Newton step of unit length in z, so L-BFGS-B's unit first step is already
    the right one."""

    def whiten(self, v: Array) -> Array:
        raise NotImplementedError

    def set_step(self, grad_g: Array) -> None:
        n = float(np.linalg.norm(self.whiten(grad_g)))
        self.c = n if n > 0 else 1.0

    def grad_z(self, grad_g: Array) -> Array:
        """Chain rule through g = c L^-T z, with the objective divided by c^2."""
        return self.whiten(grad_g) / self.c

    @property
    def value_scale(self) -> float:
        return self.c * self.c


class LowRankPreconditioner(_Whitened):
    """H = Q S Q^T + lam (I - Q Q^T), applied through L = Q L_S Q^T + sqrt(lam) (I - Q Q^T)
    (S = L_S L_S^T). Q's products run in its dtype (float32
    for the network, whose gradients carry no more digits). Shape: Q (K, r), S (r, r)."""

    def __init__(self, Q: Array, S: Array, lam: float) -> None:
        self.Q = Q
        L = sla.cholesky(S, lower=True, check_finite=False)
        Linv = sla.solve_triangular(L, np.eye(len(S)), lower=True, check_finite=False)
        self.root = float(np.sqrt(lam))
        # the r x r parts less the null part's scale: one product with Q and one with Q^T each
        self._fwd = (L.T - self.root * np.eye(len(S))).astype(Q.dtype)  # to_z
        self._inv = (Linv - np.eye(len(S)) / self.root).astype(Q.dtype)  # whiten
        self.c = 1.0

    def whiten(self, v: Array) -> Array:
        """L^-1 v = v / sqrt(lam) + Q (L_S^-1 - I / sqrt(lam)) Q^T v."""
        a = self.Q.T @ v.astype(self.Q.dtype)
        return v / self.root + (self.Q @ (self._inv @ a)).astype(np.float64)

    def to_g(self, z: Array) -> Array:
        a = self.Q.T @ z.astype(self.Q.dtype)
        return self.c * (z / self.root + (self.Q @ (self._inv.T @ a)).astype(np.float64))

    def to_z(self, g: Array) -> Array:
        a = self.Q.T @ g.astype(self.Q.dtype)
        return (self.root * g + (self.Q @ (self._fwd @ a)).astype(np.float64)) / self.c


def gauss_newton(
    U: Array,
    Q: Array,
    faces: Array,
    bary: Array,
    normals: Array,
    alpha: float,
    weights: Array | None = None,
    damping: float = 0.3,
    null: float = 0.3,
) -> LowRankPreconditioner:
    """The damped Gauss-Newton model at the points' current closest triangles.

    S = (1/m) N^T W N + (alpha + damping s) I,  lam = alpha + null s,  s = tr(N^T W N / m) / r:
    the damping keeps the step inside the region where the rest Jacobian holds; `null` gives
    the directions the rest response does not see (the nonlinear model moves them a little) a
    curvature of the same order, instead of alpha's, which would make them explode. Both were
    chosen on the beam (0.3, 0.3: 44 iterations from rest against 133 without; 1e-3 led to
    wrong shapes). Shape: U (3p, r), Q (K, r).
    """
    N = residual_rows(U, faces, bary, normals)
    m = len(N)
    Nw = N if weights is None else N * weights[:, None].astype(N.dtype)
    S = (Nw.T @ N).astype(np.float64) / m
    s = float(np.trace(S)) / len(S)
    S[np.diag_indices_from(S)] += alpha + damping * s
    return LowRankPreconditioner(Q, S, alpha + null * s)


class Preconditioner(_Whitened):
    """g = c L^-T z for a dense H = L L^T (the carried curvature)."""

    def __init__(self, H: Array) -> None:
        # Fortran order for BLAS; each evaluation then whitens with one triangular solve (BLAS
        # trsv: 14 us at K = 180, against 9 us for a product with an explicit L^-1, whose
        # forming cost 0.64 ms per frame there and grows as K^3)
        self.L = np.asfortranarray(sla.cholesky(H, lower=True, check_finite=False))
        self.c = 1.0

    def whiten(self, v: Array) -> Array:
        return dtrsv(self.L, v, lower=1)

    def to_g(self, z: Array) -> Array:
        return self.c * dtrsv(self.L, z, lower=1, trans=1)

    def to_z(self, g: Array) -> Array:
        return self.L.T @ g / self.c


class Curvature:
    """A dense BFGS model of Phi's Hessian in force space, carried from frame to frame.

    Consecutive frames of a stream are nearby problems with nearly the same curvature, but
    L-BFGS-B starts every frame with an empty memory. This keeps what the past frames measured
    (pairs s = g_{k+1} - g_k, y = grad_{k+1} - grad_k along accepted iterates) in a matrix B,
    and the next frame runs in variables whitened by B, so its first step is already a
    quasi-Newton step. Curvature is measured at the current deformation, unlike a Jacobian taken
    at rest. Shape: B (K, K), K = 3 x support size.
    """

    def __init__(self, size: int, max_size: int = 600) -> None:
        self.size = size
        self.enabled = size <= max_size  # a K^3 Cholesky per frame stays cheap below this
        self.B: Array | None = None
        self.pairs = 0

    def update(self, gs: list[Array], grads: list[Array], recent: int = 40) -> None:
        """BFGS updates with the pairs of one frame's last `recent` accepted iterates (skips
        those with too little curvature, so B stays positive definite). Each pair costs two
        K x K outer products: the cap bounds a long frame's bookkeeping (200 pairs on a
        360-force support took 0.46 s), and the last pairs measure the curvature near the
        optimum, where the next frame starts."""
        if not self.enabled:
            return
        for k in range(max(0, len(gs) - 1 - recent), len(gs) - 1):
            s, y = gs[k + 1] - gs[k], grads[k + 1] - grads[k]
            sy = float(s @ y)
            if sy <= 1e-8 * float(np.linalg.norm(s) * np.linalg.norm(y)) or sy <= 0:
                continue
            if self.B is None:
                self.B = np.asfortranarray(np.eye(self.size) * (float(y @ y) / sy))
            Bs = self.B @ s
            sBs = float(s @ Bs)
            # two rank-one updates in place (BLAS ger on the Fortran-ordered, symmetric B)
            self.B = dger(1.0 / sy, y, y, a=self.B, overwrite_a=True)
            self.B = dger(-1.0 / sBs, Bs, Bs, a=self.B, overwrite_a=True)
            self.pairs += 1

    def preconditioner(self, grad: Array) -> Preconditioner | None:
        if self.B is None:
            return None
        try:
            P = Preconditioner(0.5 * (self.B + self.B.T))
        except np.linalg.LinAlgError:  # lost definiteness to roundoff: start again
            self.B = None
            return None
        P.set_step(grad)
        return P

    def shift(self, d: float) -> None:
        """The regulariser's weight moved by d: its Hessian is alpha I, so B moves by d I."""
        if self.B is not None and d != 0.0:
            self.B[np.diag_indices_from(self.B)] += d

    def reset(self) -> None:
        self.B, self.pairs = None, 0

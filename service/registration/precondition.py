"""A Gauss-Newton preconditioner for the registration problem.

Registration is a nonlinear least-squares problem: with r_j the signed point-to-plane residual
of point j (normal of its closest triangle), the Hessian of Phi(g) = J + alpha/2 |g|^2 is close
to  H = (1/m) A^T A + alpha I,  A_j = dr_j/dg = sum_v w_jv n_j^T B_v,  where B = du/dg is the
forward model's Jacobian (rows of the nodes of the closest triangles, barycentric weights w).
Forces on neighbouring nodes move the surface almost alike, so H is badly conditioned and plain
L-BFGS needs tens of iterations; in the variables z = L^T g (H = L L^T) the curvature is close
to the identity and it needs a handful.

B is the model's Jacobian at rest (the small-strain response), computed once per operator: an
approximation is all a preconditioner needs, and the optimisation itself uses exact gradients.
With bounds on g only a diagonal scaling keeps them a box, so then D = sqrt(diag H) is used.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
from scipy.linalg.blas import dger

Array = np.ndarray


def residual_jacobian(jac: Array, faces: Array, bary: Array, normals: Array) -> Array:
    """A: d(point-to-plane residual)/dg for every point.

    Shape: jac (p, 3, K) node-major Jacobian of the matching nodes' displacement; faces (m, 3)
    local node ids of each point's closest triangle; bary (m, 3); normals (m, 3) -> (m, K).
    """
    coef = bary[:, :, None] * normals[:, None, :]  # (m, 3 corners, 3 axes)
    return np.einsum("mvd,mvdk->mk", coef, jac[faces], optimize=True)


def gauss_newton_hessian(A: Array, alpha: float, weights: Array | None = None, damping: float = 1e-3) -> Array:
    """H = (1/m) A^T W A + (alpha + mu) I, mu = damping x its mean curvature.

    The Levenberg-Marquardt term mu matters: forces the visible points barely see have almost
    no curvature, and an undamped Gauss-Newton step would move them without limit (the true,
    nonlinear problem does not stay quadratic that far). Shape: A (m, K) -> (K, K).
    """
    m = A.shape[0]
    Aw = A if weights is None else A * weights[:, None]
    H = (Aw.T @ A) / m
    mu = damping * float(np.trace(H)) / H.shape[0]
    H[np.diag_indices_from(H)] += alpha + mu
    return H


class Preconditioner:
    """g = c L^-T z (full) or g = c D^-1 z (diagonal); c makes the first Gauss-Newton step of
    length one in z, so L-BFGS-B's unit first step is already the right one."""

    def __init__(self, H: Array, diagonal: bool = False) -> None:
        self.diagonal = diagonal
        if diagonal:
            self.d = np.sqrt(np.maximum(np.diag(H), 1e-300))
        else:
            self.L = sla.cholesky(H, lower=True, check_finite=False)
            # L^-1 once: every evaluation then whitens with a matrix-vector product instead of
            # a triangular solve's call overhead (K <= 600, so K^2 floats is small)
            self.Linv = sla.solve_triangular(self.L, np.eye(len(H)), lower=True, check_finite=False)
        self.c = 1.0

    def set_step(self, grad_g: Array) -> None:
        """Choose c from the gradient at the start: |GN step| in z = |L^-1 grad| / c = 1."""
        n = float(np.linalg.norm(self.whiten(grad_g)))
        self.c = n if n > 0 else 1.0

    def whiten(self, v: Array) -> Array:
        """L^-1 v (or v / d)."""
        if self.diagonal:
            return v / self.d
        return self.Linv @ v

    def to_g(self, z: Array) -> Array:
        if self.diagonal:
            return self.c * z / self.d
        return self.c * (self.Linv.T @ z)

    def to_z(self, g: Array) -> Array:
        if self.diagonal:
            return g * self.d / self.c
        return self.L.T @ g / self.c

    def grad_z(self, grad_g: Array) -> Array:
        """Chain rule through g = c L^-T z, with the objective divided by c^2."""
        return self.whiten(grad_g) / self.c

    @property
    def value_scale(self) -> float:
        return self.c * self.c


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

    def preconditioner(self, grad: Array) -> "Preconditioner | None":
        if self.B is None:
            return None
        try:
            P = Preconditioner(0.5 * (self.B + self.B.T))
        except np.linalg.LinAlgError:  # lost definiteness to roundoff: start again
            self.B = None
            return None
        P.set_step(grad)
        return P

    def reset(self) -> None:
        self.B, self.pairs = None, 0

"""The FEM's Jacobians du/dg: formed in full (`DenseJacobian`), a large support's leading
directions (`LowRankJacobian`), and as products, a solve each (`JacobianProducts`).

They serve the Jacobian protocol (forward.py), as the reduced network's CoefficientJacobian
(surrogate/jacobian.py) does; FEMOperator (fem/model.py) makes them.
"""

from __future__ import annotations

import time

import numpy as np

from ..forward import ForwardFailed

Array = np.ndarray


class JacobianProducts:
    """du/dg at one g as products, each one solve with the exact tangent's factor there (K =
    3k force components, p the operator's nodes); `held`, a :class:`DenseJacobian` formed in
    full at an earlier g, preconditions them (levenberg.KrylovGaussNewton). Past `deadline`
    a product gives up (ForwardFailed "time_limit")."""

    def __init__(
        self, ready, solve, cols: Array, read: Array, n_free: int, held: DenseJacobian, deadline: float | None
    ) -> None:
        self.ready, self._solve, self._cols, self._read, self._n_free = ready, solve, cols, read, n_free
        self._moving = read >= 0
        self.held, self.deadline = held, deadline
        self.n_rows, self.n_solves = read.size, 0

    def _solved(self, rhs: Array) -> Array:
        if self.deadline is not None and time.perf_counter() > self.deadline:
            raise ForwardFailed("time_limit", f"time budget spent in the Jacobian's products, after {self.n_solves}")
        self.n_solves += 1
        return self._solve(rhs)

    def matvec(self, x: Array) -> Array:
        """(du/dg) x. Shape: (K,) -> (3p,) node-major."""
        rhs = np.zeros(self._n_free)
        rhs[self._cols] = x
        out = np.zeros(self.n_rows)
        out[self._moving] = self._solved(rhs)[self._read[self._moving]]
        return out

    def rmatvec(self, y: Array) -> Array:
        """(du/dg)^T y (the tangent is symmetric: one solve). Shape: (3p,) -> (K,)."""
        rhs = np.zeros(self._n_free)
        rhs[self._read[self._moving]] = y[self._moving]  # the nodes are distinct
        return self._solved(rhs)[self._cols]


class DenseJacobian:
    """du/dg as it is: U (3p, K) node-major over the operator's nodes, C the identity (the
    FEM's Jacobian, K = 3 x support nodes, float64)."""

    def __init__(self, U: Array) -> None:
        self.U = np.ascontiguousarray(U, np.float64)

    def gram(self) -> Array:
        """C C^T: the identity (K, K), float64, read-only."""
        eye = np.eye(self.U.shape[1])
        eye.flags.writeable = False
        return eye

    def gram_product(self, A: Array) -> Array:
        """C C^T A = A, Fortran-ordered (A symmetric): no product with the identity."""
        return A.T

    def matvec(self, v: Array) -> Array:
        return np.asarray(v, np.float64).ravel()

    def rmatvec(self, w: Array) -> Array:
        return np.asarray(w, np.float64).ravel()


class LowRankJacobian(DenseJacobian):
    """du/dg ~ U C with C's rows orthonormal (r, K): a large support's rest Jacobian, for the
    error estimate alone (FEMOperator._rest_low_rank). C C^T is the identity (r, r), so its
    Gram products are the dense Jacobian's."""

    def __init__(self, U: Array, C: Array) -> None:
        super().__init__(U)
        self.C = np.ascontiguousarray(C, np.float64)

    def matvec(self, v: Array) -> Array:
        return self.C @ np.asarray(v, np.float64).ravel()

    def rmatvec(self, w: Array) -> Array:
        return self.C.T @ np.asarray(w, np.float64).ravel()

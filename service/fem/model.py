"""The finite-element forward model: Newton for g -> u, the transposed tangent for the adjoint.

This is the paper's classical (accurate, slow) method behind the same interface as the network.
Each operator owns a Newton solver (its own factorisation) and warm-starts every solve from the
previous equilibrium, so successive L-BFGS evaluations cost a couple of Newton steps each.
"""

from __future__ import annotations

import dataclasses
from functools import cached_property

import numpy as np

from ..mesh import TetMesh
from ..registration.forward import ForwardFailed, check_support
from .assembly import Assembler
from .linsolve import make_solver
from .material import NeoHookean
from .newton import NewtonOptions, NewtonResult, NewtonSolver

Array = np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class FEMModel:
    """Neo-Hookean FEM on a mesh. Immutable; share it between sessions."""

    mesh: TetMesh
    material: NeoHookean
    options: NewtonOptions = NewtonOptions()

    method = "fem"

    @cached_property
    def assembler(self) -> Assembler:
        return Assembler(self.mesh, self.material)

    def with_stiffness(self, E: float) -> "FEMModel":
        return FEMModel(self.mesh, self.material.with_stiffness(E), self.options)

    def newton(self) -> NewtonSolver:
        """A fresh solver (owns a factorisation: one per thread)."""
        return NewtonSolver(self.assembler, self.options)

    def solve(self, forces: Array, support: Array, u0: Array | None = None) -> NewtonResult:
        """Equilibrium under `forces` (k, 3) on `support` (k,). Shape: result.u (n, 3)."""
        g = np.zeros((self.mesh.n_nodes, 3))
        g[check_support(self.mesh, support)] = forces
        return self.newton().solve(g, u0)

    def restrict(self, support: Array, nodes: Array | None = None) -> "FEMOperator":
        return FEMOperator(self, support, nodes)


class FEMOperator:
    """Forces on a support -> displacement of some nodes, with the adjoint as pullback.

    The adjoint solves K(u) p = u_bar (K is symmetric) with the tangent factorised at the
    converged u (refined on a shifted factor where u is unstable), so the gradient is that of
    the converged solution, not of an earlier iterate; the next evaluation starts from u and
    uses that factor for its predictor and as its Newton steps' preconditioner.
    """

    def __init__(self, model: FEMModel, support: Array, nodes: Array | None = None) -> None:
        self.model = model
        self.mesh = model.mesh
        self.support = check_support(model.mesh, support)
        self.nodes = np.arange(model.mesh.n_nodes) if nodes is None else np.asarray(nodes, np.int64)
        self._newton = model.newton()
        self._u: Array | None = None  # last equilibrium: the next solve's start
        self._rest = None
        self._low_rank: tuple[Array, Array] | None = None
        self.last: NewtonResult | None = None

    def reset(self) -> None:
        self._u = None

    def _solve(self, g: Array) -> NewtonResult:
        G = np.zeros((self.mesh.n_nodes, 3))
        G[self.support] = g
        res = self._newton.solve(G, self._u)
        self.last = res
        if not res.converged:
            raise ForwardFailed(res.status, f"Newton residual {res.residual:.2e} after {res.iterations} iterations")
        self._u = res.u
        return res

    def displacement(self, g: Array) -> Array:
        return self._solve(np.asarray(g, np.float64)).u

    def _rest_solver(self):
        """Factorisation of the rest stiffness, made on first use (the rest state's adjoint)."""
        if self._rest is None:
            K0 = self.model.assembler.stiffness_at_rest()
            solver = make_solver(K0, self.model.options.backend)
            solver.factor(K0)
            self._rest = solver
        return self._rest

    def low_rank_jacobian(self, rank: int = 128) -> tuple[Array, Array]:
        """du/dg at rest (small strain) on the operator's nodes as U Q^T, Q orthonormal: 3k
        solves with the rest factorisation, then a truncated SVD (the Gauss-Newton
        preconditioner's input; the compliance's spectrum decays fast, so r modes carry it).
        Cached. Shape: U (3p, r) node-major, Q (3k, r)."""
        if self._low_rank is None:
            mesh, k = self.mesh, self.support.size
            rhs = np.zeros((3 * mesh.n_nodes, 3 * k))
            rows = (3 * self.support[:, None] + np.arange(3)).ravel()
            rhs[rows, np.arange(3 * k)] = 1.0
            X = np.zeros_like(rhs)
            X[mesh.free_dofs] = self._rest_solver().solve(rhs[mesh.free_dofs])
            J = X.reshape(mesh.n_nodes, 3, 3 * k)[self.nodes].reshape(3 * self.nodes.size, 3 * k)
            W, sv, Vt = np.linalg.svd(J, full_matrices=False)
            r = max(1, min(rank, int(np.count_nonzero(sv > 1e-8 * sv[0]))))
            self._low_rank = (np.ascontiguousarray(W[:, :r] * sv[:r]), np.ascontiguousarray(Vt[:r].T))
        return self._low_rank

    def __call__(self, g: Array) -> tuple[Array, callable]:
        g = np.asarray(g, np.float64)
        if not np.any(g):  # zero load: the rest state, exactly; keeps the warm start intact
            asm, solver = self.model.assembler, self._rest_solver()
            nodes, support, mesh = self.nodes, self.support, self.mesh

            def rest_pullback(u_bar: Array, rows: Array | None = None) -> Array:
                rhs = np.zeros((mesh.n_nodes, 3))
                np.add.at(rhs, nodes, u_bar)
                return asm.unpack(solver.solve(asm.pack(rhs)))[support]

            return np.zeros((nodes.size, 3)), rest_pullback
        res = self._solve(g)
        asm, newton = self.model.assembler, self._newton
        u = res.u
        nodes, support, mesh = self.nodes, self.support, self.mesh

        def pullback(u_bar: Array, rows: Array | None = None) -> Array:
            rhs = np.zeros((mesh.n_nodes, 3))
            np.add.at(rhs, nodes, u_bar)
            b = asm.pack(rhs)
            # the exact tangent at the solution: the adjoint is one solve, and the next
            # evaluation (warm-started from u) uses this factor for its predictor and as its
            # Newton steps' preconditioner (conjugate gradients on a nearby factor would need
            # 15 solves for the adjoint's 1e-10, more than a factorisation, measured)
            if newton.factor_at(u):
                p = newton.solver.solve(b)
            else:  # an unstable equilibrium: refine on the shifted factor
                p = _refined_solve(asm.tangent(u), newton.solver.solve, b)
            return asm.unpack(p)[support]

        return u[nodes], pullback


def _refined_solve(K, approx_solve, b: Array, rtol: float = 1e-10, max_steps: int = 6) -> Array:
    """Solve K x = b by iterative refinement on a nearby factorisation (approx_solve ~ K^-1)."""
    x = approx_solve(b)
    bn = np.linalg.norm(b) or 1.0
    for _ in range(max_steps):
        r = b - K @ x
        if np.linalg.norm(r) <= rtol * bn:
            break
        x = x + approx_solve(r)
    return x

"""The finite-element forward model: Newton for g -> u, the transposed tangent for the adjoint.

This is the paper's classical (accurate, slow) method behind the same interface as the network.
Each operator owns a Newton solver (its own factorisation) and warm-starts every solve from the
previous equilibrium, so successive L-BFGS evaluations cost a couple of Newton steps each.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator
from functools import cached_property

import numpy as np

from ..forward import ForwardFailed, check_support
from ..mesh import TetMesh
from .assembly import Assembler
from .jacobian import DenseJacobian, JacobianProducts, LowRankJacobian
from .linsolve import SparseSolver, make_solver, refined_solve
from .material import NeoHookean
from .newton import NewtonOptions, NewtonResult, NewtonSolver
from .response import Solve, support_response
from .rest import OVERSAMPLE, POWER, RestCompliance, leading_directions, rest_compliance

Array = np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class FEMModel:
    """Neo-Hookean FEM on a mesh. Immutable; share it between sessions."""

    mesh: TetMesh
    material: NeoHookean
    options: NewtonOptions = NewtonOptions()
    #: N, the largest total force a tool exerts on this organ (the scene's [training] max_force):
    #: the error estimate's prior on the forces a cloud does not determine; None: no prior
    max_force: float | None = None
    #: nodes a tool's force spreads over at most (the upper end of the scene's [training]
    #: patch_nodes): where a support is larger than a tool's margin, the prior's windows
    tool_patch: int | None = None

    method = "fem"

    @cached_property
    def assembler(self) -> Assembler:
        return Assembler(self.mesh, self.material)

    def with_stiffness(self, E: float) -> FEMModel:
        # the same problem in forces scaled by E / E_now: the largest tool force too (the estimate's prior)
        scaled = None if self.max_force is None else self.max_force * (E / self.material.E)
        new = dataclasses.replace(self, material=self.material.with_stiffness(E), max_force=scaled)
        if "assembler" in self.__dict__:  # the sparsity pattern is the mesh's (0.3 s on the liver to remake)
            new.__dict__["assembler"] = self.assembler.with_material(new.material)
        return new

    def newton(self) -> NewtonSolver:
        """A fresh solver (owns a factorisation: one per thread)."""
        return NewtonSolver(self.assembler, self.options)

    def solve(
        self, forces: Array, support: Array, u0: Array | None = None, deadline: float | None = None
    ) -> NewtonResult:
        """Equilibrium under `forces` (k, 3) on `support` (k,), until `deadline` at most
        (NewtonSolver.solve). Shape: result.u (n, 3)."""
        g = np.zeros((self.mesh.n_nodes, 3))
        g[check_support(self.mesh, support)] = forces
        if deadline is not None and time.perf_counter() > deadline:  # before a solver's rest stiffness is made
            u = np.zeros_like(g) if u0 is None else self.mesh.unpack(self.mesh.pack(np.asarray(u0, np.float64)))
            return NewtonResult(u, False, "time_limit", 0, 0, [], 0.0)  # the start, as NewtonSolver's
        return self.newton().solve(g, u0, deadline)

    def restrict(self, support: Array, nodes: Array | None = None) -> FEMOperator:
        return FEMOperator(self, support, nodes)


#: The largest support whose Jacobian the FEM forms (3 solves a node at each Levenberg-Marquardt
#: step; the paper's liver with its 60 nodes: 0.3 s on 2 cores; the whole 1,500-node liver
#: surface would take about 8 s and 100 MB a step)
MAX_JACOBIAN_SUPPORT = 500
#: the directions a larger support's rest Jacobian keeps for the error estimate (as the network's
#: linear block keeps: the compliance's spectrum decays fast)
ESTIMATE_RANK = 64

#: Equilibria an operator keeps by their forces, the latest first: a frame's outputs are taken
#: at its best iterate, which need not be its last evaluation (a frame cut short by its budget
#: mid line search), and solving for it again would be a Newton solve past the budget. 32
#: covers a whole L-BFGS-B line search (30 trials at most) or Levenberg-Marquardt's 7 rejected
#: steps after the best (the best itself is pinned past them: FEMOperator.pin); on the paper's
#: liver they hold 2.3 MB
KEPT_EQUILIBRIA = 32


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
        self._rest: RestCompliance | None = None
        self._low_rank: tuple[Array, Array] | None = None
        # (g, u) of recent equilibria, latest first; the first is the next solve's start
        self._kept: list[tuple[Array, Array]] = []
        # a frame's best equilibrium (:meth:`pin`), past the list: its outputs are read there
        self._pinned: tuple[Array, Array] | None = None
        self._rest_jacobian: DenseJacobian | None = None
        self._unread_rows: Array | None = None  # the rest solves' rows at _unread, until readout_at takes them
        self._rest_leading: LowRankJacobian | None = None  # a large support's, for the estimate
        self._helper: SparseSolver | None = None  # a second factor, for the Jacobian's other half
        self._last_jacobian: tuple[Array, DenseJacobian] | None = None  # (g, du/dg at g)
        self._held: DenseJacobian | None = None  # the latest Jacobian formed in full, at any g
        self.n_jacobians = 0  # Jacobians formed in full away from rest (only grows)
        self.last: NewtonResult | None = None
        #: a time.perf_counter() value past which solves give up (ForwardFailed "time_limit"):
        #: the engine sets it for the length of a frame with a time budget
        self.deadline: float | None = None

    def reset(self) -> None:
        self._kept = []
        self._pinned = None
        self._last_jacobian = None
        self._held = None

    @property
    def _last_u(self) -> Array | None:
        """The latest equilibrium (the next solve's start), None before the first."""
        return self._kept[0][1] if self._kept else None

    def _starts(self, g: Array) -> Iterator[Array | None]:
        """Where a solve for g starts: the latest equilibrium; should Newton fail from there, the
        kept equilibria (rest among them) whose forces are nearer g than the latest's, nearest
        first, two at most. A far trial step leaves a start Newton cannot come back from to
        forces it had just solved; a far trial itself has no nearer start, and fails at once."""
        if not self._kept:
            yield None
            return
        latest_g, latest_u = self._kept[0]
        yield latest_u
        near = float(np.linalg.norm(latest_g - g))
        others = [(float(np.linalg.norm(kg - g)), u) for kg, u in self._kept[1:]]
        others.append((float(np.linalg.norm(g)), None))  # rest
        for _, u in sorted((o for o in others if o[0] < near), key=lambda o: o[0])[:2]:
            yield u

    def pin(self, g: Array) -> None:
        """Keeps the equilibrium under g, the latest evaluated (a frame's new best iterate), until
        the next pin or reset, however many solves follow: more than KEPT_EQUILIBRIA after it
        evicted it, and the frame's outputs solved for it again with no deadline."""
        if self._kept and np.array_equal(self._kept[0][0], g):
            self._pinned = self._kept[0]

    def _solve(self, g: Array) -> NewtonResult:
        G = np.zeros((self.mesh.n_nodes, 3))
        G[self.support] = g
        for u0 in self._starts(g):
            res = self._newton.solve(G, u0, self.deadline)
            if res.converged or res.status == "time_limit":
                break
        self.last = res
        if res.status == "time_limit":
            raise ForwardFailed(res.status, f"time budget spent in a Newton solve, after {res.iterations} iterations")
        if not res.converged:  # res.residual unread: an internal-force pass per failed trial, for words
            raise ForwardFailed(
                res.status, f"no equilibrium after {res.iterations} iterations ({res.load_steps} load steps completed)"
            )
        self._kept = [(np.array(g, np.float64), res.u), *self._kept[: KEPT_EQUILIBRIA - 1]]
        return res

    def displacement(self, g: Array) -> Array:
        """The equilibrium under g (:meth:`_equilibrium`), the caller's to change."""
        return self._equilibrium(np.asarray(g, np.float64)).copy()

    def _equilibrium(self, g: Array) -> Array:
        """The equilibrium under g: a kept one if g was solved lately (the state the optimiser
        scored, at no cost; a warm frame's start is the last frame's answer), else a Newton
        solve. The next solve starts from it either way. Read-only. Shape: (n, 3).
        Zero load is the rest state, exactly and at no cost, as an evaluation takes it: a solve
        back to rest from the latest equilibrium took a frame's outputs 3-4 s past its budget
        (the phantom, E 4.5, a frame whose best iterate was the rest state)."""
        if not np.any(g):
            return np.zeros((self.mesh.n_nodes, 3))
        for i, (g_kept, u_kept) in enumerate(self._kept):
            if np.array_equal(g_kept, g):
                self._kept.insert(0, self._kept.pop(i))  # the latest now
                return u_kept
        pinned = self._pinned
        if pinned is not None and np.array_equal(pinned[0], g):  # evicted from the list: back in it
            self._kept = [pinned, *self._kept[: KEPT_EQUILIBRIA - 1]]
            return pinned[1]
        return self._solve(g).u

    def _rest_solver(self) -> RestCompliance:
        """The rest stiffness's factorisation (the rest state's adjoint), shared with every
        model and session on this mesh and material, fetched on first use."""
        if self._rest is None:
            self._rest = rest_compliance(self.mesh, self.model.assembler.material, self.model.options.backend)
        return self._rest

    def low_rank_jacobian(self, rank: int = 128) -> tuple[Array, Array]:
        """du/dg at rest (small strain) on the operator's nodes as U Q^T, Q orthonormal: 3k
        solves with the rest factorisation, then a truncated SVD (the Gauss-Newton
        preconditioner's input; the compliance's spectrum decays fast, so r modes carry it).
        Cached. Shape: U (3p, r) node-major, Q (3k, r)."""
        if self._low_rank is None:
            J = self._rest_dense().U
            W, sv, Vt = np.linalg.svd(J, full_matrices=False)
            r = max(1, min(rank, int(np.count_nonzero(sv > 1e-8 * sv[0]))))
            self._low_rank = (np.ascontiguousarray(W[:, :r] * sv[:r]), np.ascontiguousarray(Vt[:r].T))
        return self._low_rank

    @property
    def has_jacobian(self) -> bool:
        """Whether :meth:`jacobian` serves this support (MAX_JACOBIAN_SUPPORT nodes at most)."""
        return self.support.size <= MAX_JACOBIAN_SUPPORT

    def jacobian(self, g: Array) -> DenseJacobian:
        """du/dg at g on the operator's nodes (the Levenberg-Marquardt driver's model): 3k
        solves with the exact tangent's factorisation at g's equilibrium (:meth:`_equilibrium`:
        the kept one if g was solved lately; the factor is the last evaluation's when g was
        evaluated last, as the driver asks right after). Kept for the rest state and the last g:
        a warm-started frame starts where the last one ended. Shape: U (3p, 3k)."""
        if not self.has_jacobian:
            raise ValueError(
                f"levenberg-marquardt with the fem method takes 3 solves per support node at each step: at most "
                f"{MAX_JACOBIAN_SUPPORT} support nodes (this support has {self.support.size}); use optimizer 'lbfgsb'"
            )
        g = np.asarray(g, np.float64)
        if not np.any(g):
            self._held = self._rest_dense()
            return self._held
        if self._last_jacobian is not None and np.array_equal(self._last_jacobian[0], g):
            return self._last_jacobian[1]
        newton, u = self._newton, self._equilibrium(g)
        if newton.factor_at(u):
            jac = DenseJacobian(self._support_response(newton.solver.solve, self.deadline, at=u))
        else:  # an unstable equilibrium: refine on the shifted factor
            K = self.model.assembler.tangent(u)
            solve = lambda B: refined_solve(K, newton.solver.solve, B)  # noqa: E731
            jac = DenseJacobian(self._support_response(solve, self.deadline))
        self._last_jacobian = (g.copy(), jac)
        self._held = jac
        self.n_jacobians += 1
        return jac

    def estimate_jacobian(self, g: Array) -> DenseJacobian | LowRankJacobian:
        """du/dg for the error estimate (registration/confidence.py), with no solve at g: the
        rest one (3k solves with the rest factor, once per operator), whose Gram the session
        keeps: which force directions a cloud leaves undetermined is a matter of where it looks
        more than of the load, and the one Levenberg-Marquardt formed at the answer cost a
        Newton frame 7-27 % in a new Gram (docs/performance.md). Past MAX_JACOBIAN_SUPPORT
        support nodes, its leading ESTIMATE_RANK directions (:meth:`_rest_low_rank`)."""
        return self._rest_dense(readout=True) if self.has_jacobian else self._rest_low_rank()

    @cached_property
    def _unread(self) -> Array:
        """The surface nodes the objective does not read: where the estimate's spread reads the
        rest of the surface (registration/outputs.py asks :meth:`readout_at` there)."""
        return np.setdiff1d(self.mesh.surface_nodes, self.nodes)

    def _rest_low_rank(self) -> LowRankJacobian:
        """du/dg at rest, its leading ESTIMATE_RANK directions by rest.leading_directions (480
        solves with the rest factor, however large the support), made once: a large support's
        estimate then has the force prior's term (without it, a one-point cloud on the phantom's
        592-node region read 0.000 mm on a true 3.4 mm). The directions are chosen on the
        objective's nodes and the rest of the surface, which :meth:`readout_at` reads along them."""
        if self._rest_leading is None:
            cols, own = self._dof_maps
            # the estimate reads the whole surface: directions chosen on the matched nodes alone
            # missed the forces that move the rest (two matched triangles: 1.9 mm at 501 support
            # nodes where the dense Jacobian read 16.6 mm at 500)
            read = np.concatenate([own, self._free_rows(self._unread)])
            solve, n_free = self._rest_solver().solve_free, self.mesh.free_dofs.size
            moving = read >= 0

            def forward(X: Array) -> Array:  # J X: unit forces on the support, read at the nodes
                return self._rest_response(X, read)

            def back(Y: Array) -> Array:  # J^T Y: the rest stiffness is symmetric
                rhs = np.zeros((n_free, Y.shape[1]))
                rhs[read[moving]] = Y[moving]  # the nodes are distinct
                return solve(rhs)[cols]

            U, C = leading_directions(forward, back, cols.size, ESTIMATE_RANK, OVERSAMPLE, POWER)
            self._rest_leading = LowRankJacobian(U[: own.size], C)  # the objective's rows
        return self._rest_leading

    def readout_at(self, nodes: Array) -> Array:
        """The rows at other nodes (3q, its columns) of :meth:`estimate_jacobian`, the rest one:
        the error estimate's spread reads the whole surface, not the objective's nodes alone.
        At the surface nodes the objective does not read (the session's ask), the rows the rest
        Jacobian's own solves read, handed over once (the session keeps their Gram); at other
        nodes 3 solves per support node with the rest factor. Past MAX_JACOBIAN_SUPPORT, one
        solve per leading direction."""
        if not self.has_jacobian:
            return self._rest_response(self._rest_low_rank().C.T, self._free_rows(nodes))
        if np.array_equal(nodes, self._unread):
            self._rest_dense(readout=True)
            rows, self._unread_rows = self._unread_rows, None
            if rows is not None:
                return rows
        return self._support_response(self._rest_solver().solve_free, read=self._free_rows(nodes))

    def _rest_response(self, X: Array, read: Array) -> Array:
        """The rest compliance applied to forces X (3k, m) on the support, read at the free
        system's rows `read` (-1: a fixed dof, zero). Shape: (read.size, m)."""
        cols, _ = self._dof_maps
        rhs = np.zeros((self.mesh.free_dofs.size, X.shape[1]))
        rhs[cols] = X
        out = np.zeros((read.size, X.shape[1]))
        moving = read >= 0
        out[moving] = self._rest_solver().solve_free(rhs)[read[moving]]
        return out

    def _rest_dense(self, readout: bool = False) -> DenseJacobian:
        """du/dg at rest, formed in full once (3k solves with the rest factorisation). `readout`
        (the error estimate's): the same solves read at :attr:`_unread` too, kept for
        :meth:`readout_at`: solving them again only to read other rows took a session open with
        `matching` at 300 support nodes from 0.20 to 0.36 s (docs/performance.md)."""
        if self._rest_jacobian is None:
            _, own = self._dof_maps
            unread = self._unread if readout else self._unread[:0]
            read = np.concatenate([own, self._free_rows(unread)])
            J = self._support_response(self._rest_solver().solve_free, read=read)
            # the objective's rows copied where there are others: not a view that holds them for good
            self._rest_jacobian = DenseJacobian(J[: own.size].copy() if unread.size else J)
            self._unread_rows = J[own.size :] if unread.size else None
        return self._rest_jacobian

    def jacobian_products(self, g: Array) -> JacobianProducts | None:
        """du/dg at g as products, one solve each with the exact tangent's factor at g's
        equilibrium, and the latest Jacobian formed in full (at an earlier g) to precondition
        them: a Levenberg-Marquardt step in a few solves, not 3k. None where :meth:`jacobian`
        is as cheap or the products cannot be had: at rest, at the g of the last Jacobian,
        before any was formed, at an unstable equilibrium."""
        g = np.asarray(g, np.float64)
        last = self._last_jacobian
        if self._held is None or not np.any(g) or (last is not None and np.array_equal(last[0], g)):
            return None
        newton, u = self._newton, self._equilibrium(g)

        def ready() -> bool:  # a trial evaluated since may have left its own factor
            return newton.factor_at(u)

        if not ready():
            return None
        cols, read = self._dof_maps
        n_free = self.mesh.free_dofs.size
        return JacobianProducts(ready, newton.solver.solve, cols, read, n_free, self._held, self.deadline)

    @cached_property
    def _dof_maps(self) -> tuple[Array, Array]:
        """Rows of the free system: the support's (3k,) and the operator's nodes' (3p,), -1 on
        fixed dofs (they never move)."""
        return self._free_rows(self.support), self._free_rows(self.nodes)

    def _free_rows(self, nodes: Array) -> Array:
        """The free system's rows of these nodes' dofs (3q,), node-major, -1 on fixed dofs."""
        mesh = self.mesh
        pos = np.full(3 * mesh.n_nodes, -1, np.int64)
        pos[mesh.free_dofs] = np.arange(mesh.free_dofs.size)
        return pos[(3 * np.asarray(nodes, np.int64)[:, None] + np.arange(3)).ravel()]

    def _support_response(
        self,
        solve,
        deadline: float | None = None,
        block: int = 256,
        at: Array | None = None,
        read: Array | None = None,
    ) -> Array:
        """K^-1 applied to each unit force on the support, read at the operator's nodes
        (response.support_response); past `deadline`, ForwardFailed between blocks (the rest
        responses, made once per operator, take none). `at`: the state u whose exact tangent
        `solve` holds; given, the last columns go to a spare core, which factorises that tangent
        on a solver of its own. `read`: the free system's rows to read (:meth:`_free_rows`), else
        the operator's nodes'. Shape: (3p, 3k)."""
        cols, own = self._dof_maps
        read = own if read is None else read

        def beside() -> Solve:
            helper = self._helper_solver()
            helper.factor(self.model.assembler.tangent(at))  # at's tangent is SPD: its factor held
            return helper.solve

        return support_response(
            solve, cols, read, self.mesh.free_dofs.size, deadline, block, None if at is None else beside
        )

    def _helper_solver(self):
        """A second solver of the tangent's pattern, for columns solved on a spare core."""
        if self._helper is None:
            self._helper = make_solver(self.model.assembler.stiffness_at_rest(), self.model.options.backend)
        return self._helper

    def __call__(self, g: Array) -> tuple[Array, callable]:
        g = np.asarray(g, np.float64)
        if not np.any(g):  # zero load: the rest state, exactly; keeps the warm start intact
            asm, solver = self.model.assembler, self._rest_solver()
            nodes, support, mesh = self.nodes, self.support, self.mesh

            def rest_pullback(u_bar: Array, rows: Array | None = None) -> Array:
                rhs = np.zeros((mesh.n_nodes, 3))
                np.add.at(rhs, nodes, u_bar)
                return asm.unpack(solver.solve_free(asm.pack(rhs)))[support]

            return np.zeros((nodes.size, 3)), rest_pullback
        # a kept equilibrium, not one more Newton iteration on it: that would move u by its
        # tolerance, and the adjoint would factorise again at a state a bit away from the
        # factor the last evaluation there left (a warm Newton frame's start, every frame)
        u = self._equilibrium(g)
        asm, newton = self.model.assembler, self._newton
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
                p = refined_solve(asm.tangent(u), newton.solver.solve, b)
            return asm.unpack(p)[support]

        return u[nodes], pullback

"""Static equilibrium by Newton's method on the total energy, with line search and load stepping.

The equilibrium u_g minimises  Pi(u) = E(u) - g . u  over u with u = 0 on fixed nodes. Each
Newton step solves K du = -(f_int - g) and takes the longest step in {1, 1/2, 1/4, ...} that
lowers Pi (Armijo) and keeps every det F > 0. The step is inexact: conjugate gradients
preconditioned with the factorisation of the tangent at the solve's start, to a relative
accuracy that shrinks with the residual (so convergence stays superlinear), and a sparse direct
factorisation of the current tangent only when they would be slow (projected past
``CG_MAX_ITER``) or meet negative curvature. A factorisation costs 50 ms on the paper's liver,
a solve with it 2-4 ms: a registration's evaluation went from 2.9 factorisations to 1.1 (the
adjoint's, at the solution), same equilibria to the tolerance. An indefinite tangent is
shifted until it factorises, so every step is a descent step.

Loads are followed along a straight path from the starting state: a start u0 is in equilibrium
under its own internal force f0 = f_int(u0), so the path g(s) = f0 + s (g - f0), s in [0, 1],
begins balanced whatever u0 is. When Newton struggles at a step, the step is halved; when it
succeeds quickly, the next one doubles. A tangent predictor (one extra solve with the factor
already in hand) starts each load step. Divergence is a result (``converged=False`` with a
``status``), never an exception or a NaN.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import time
from collections import deque
from collections.abc import Callable

import numpy as np
import scipy.sparse as sp

from .assembly import Assembler
from .linsolve import NotPositiveDefinite, SparseSolver, make_solver

log = logging.getLogger(__name__)

Array = np.ndarray

#: conjugate-gradient iterations on the held factor before a Newton step factorises instead
CG_MAX_ITER = 10
#: the largest relative accuracy asked of a Newton step (inexact Newton's forcing term)
CG_FORCING = 1e-2
#: the residual a solve counts as zero, in machine epsilons of the internal forces' terms
#: (NewtonSolver.roundoff): a tiny load's relative tolerance can lie below what any iterate
#: reaches. Newton stalled at 0.3-0.6 of the estimate with one (the bar, the phantom); 4 leaves
#: a margin and decides only below strains of about 1e-5 (docs/performance.md)
ROUNDOFF_ULPS = 4.0
#: Newton iterations, the latest over this solver's solves, whose longest predicts the next's:
#: a warm evaluation takes 1-3, so these span several, a factorising iteration among them
TIMED_ITERATIONS = 16


@dataclasses.dataclass(frozen=True)
class NewtonOptions:
    """Tolerances and limits. rtol is on ||f_int - g|| / max(||g||, ||g - f_int(u0)||), free dofs."""

    rtol: float = 1e-9
    step_rtol: float = 1e-4  # looser tolerance at intermediate load steps
    max_iter: int = 100  # Newton iterations in all, over every load step
    max_step_iter: int = 12  # iterations at one load step before the step is cut
    min_load_step: float = 2.0**-10
    max_halvings: int = 30  # line search
    step_strain: float = 1.0  # largest |grad du| a load step's linear predictor may ask for
    armijo: float = 1e-4
    backend: str | None = None  # sparse solver; fastest available by default


@dataclasses.dataclass
class NewtonResult:
    """What a solve produced, converged or not.

    Shape: u (n, 3). `solver` holds the factorisation of the last tangent used (at or next to
    u), ready for adjoint solves and for predicting the next load.
    """

    u: Array
    converged: bool
    status: str  # converged | max_iter | load_step_too_small | line_search | non_finite | time_limit
    iterations: int
    load_steps: int
    residuals: list[float]
    seconds: float
    solver: SparseSolver | None = None
    shifted: int = 0  # tangents that needed a diagonal shift (indefinite)
    #: u's relative residual under the requested load, measured (None: not finite); only an
    #: unconverged result stopped before its deadline has one, read at most once (an internal-force
    #: pass: a time_limit result has none, as it would be paid past the deadline)
    measure: Callable[[], float | None] | None = dataclasses.field(default=None, repr=False)

    @functools.cached_property
    def residual(self) -> float | None:
        """||f_int(u) - g|| / max(||g||, ||g - f_int(u0)||) over the free dofs: u's relative
        residual under the requested load g, the norm rtol is on. A converged solve's is its
        last Newton residual; an unconverged one's last was of a partial load step or of an
        iterate it dropped, so u's is measured (an internal-force pass, when first read). None
        where u's internal forces are not finite, and for a time_limit result (not measured past
        its deadline)."""
        if self.converged:
            return self.residuals[-1]
        return None if self.measure is None else self.measure()


class NewtonSolver:
    """Newton's method for one mesh and material; holds the solver of its sparsity pattern.

    Not thread-safe (it owns one factorisation); make one per thread or session.
    """

    def __init__(self, assembler: Assembler, options: NewtonOptions | None = None) -> None:
        self.asm = assembler
        self.options = options or NewtonOptions()
        K0 = assembler.stiffness_at_rest()
        self.solver = make_solver(K0, self.options.backend, spare_core=True)
        self._diag = _diagonal_slots(K0)
        self._mean_diag = float(K0.diagonal().mean())
        #: the residual norm no iterate gets below: f_int sums terms vol |P| |grad N|, with
        #: stresses of the moduli's size near rest, about K0's diagonal times an element's size
        self.roundoff = ROUNDOFF_ULPS * np.finfo(float).eps * assembler.spacing * float(np.linalg.norm(K0.diagonal()))
        self._tau = 1e-4 * self._mean_diag  # last shift that worked: where the next search starts
        self._factor_x: np.ndarray | None = None  # free dofs where the factor is the exact tangent
        self._factored = False  # whether the solver holds any factor (a preconditioner)
        self._cg_skip = self._cg_backoff = 0  # Newton steps to factorise without trying CG first
        self.n_factor = 0  # factorisations made (only grows)
        self.n_cg = 0  # linear solves done by conjugate gradients on a held factor instead
        #: seconds of the latest Newton iterations, from one deadline check to the next
        self.iteration_seconds: deque[float] = deque(maxlen=TIMED_ITERATIONS)

    # -- one factorisation, shifted if indefinite ----------------------------------------------

    def factor_at(self, u: Array) -> bool:
        """Make the held factorisation the exact tangent at u (a no-op if it already is).

        Returns False if that tangent is not positive definite (an unstable state): the factor
        is then of a shifted tangent. Shape: u (n, 3).
        """
        x = self.asm.pack(u)
        if self._factor_x is not None and np.array_equal(self._factor_x, x):
            return True
        return self._factor_tangent(self.asm.tangent(u), x) == 0

    def _factor_tangent(self, K: sp.csr_matrix, x: Array) -> int:
        """Factorise the tangent K at free dofs x, remembering x when K needed no shift (the
        factor is then exactly x's tangent); returns the shifts."""
        shifts = self.factor(K)
        self._factor_x = x.copy() if shifts == 0 else None
        return shifts

    def factor(self, K: sp.csr_matrix) -> int:
        """Factorise K, adding tau I until it is positive definite; returns how many shifts."""
        self._factor_x = None
        self._factored = False
        self.n_factor += 1
        try:
            self.solver.factor(K)
            self._factored = True
            return 0
        except NotPositiveDefinite:
            pass
        base = K.data[self._diag].copy()
        tau = self._tau
        for shifts in range(1, 12):
            K.data[self._diag] = base + tau
            try:
                self.solver.factor(K)
                self._factored = True
                log.debug("tangent shifted by %.3g to factorise", tau)
                self._tau = max(tau / 10.0, 1e-8 * self._mean_diag)
                return shifts
            except NotPositiveDefinite:
                tau *= 10.0
        raise ArithmeticError("tangent could not be made positive definite")

    def solve_tangent(self, K: sp.csr_matrix, b: Array, rtol: float, max_iter: int = CG_MAX_ITER) -> Array | None:
        """K^-1 b by conjugate gradients preconditioned with the held factorisation, or None.

        The held factor is of a nearby tangent (the last state factorised: an earlier Newton
        iterate or evaluation), so M^-1 K is close to the identity and a few iterations, a
        solve and a product each, replace a factorisation (on the liver: 2.3 + 0.6 ms against
        50 ms). Stops when the preconditioned residual's norm sqrt(r' M^-1 r), about the
        error's energy norm, is rtol of the start's; gives up (None: the caller factorises K)
        after max_iter iterations or at negative curvature (K not positive definite).
        """
        if not self._factored:
            return None
        x = np.zeros_like(b)
        r = np.array(b, np.float64)
        z = self.solver.solve(r)
        rz = float(r @ z)
        if rz <= 0.0:
            return x if rz == 0.0 else None
        rz0 = rz
        stop = rtol * rtol * rz0
        p = z
        for k in range(1, max_iter + 1):
            Kp = K @ p
            pKp = float(p @ Kp)
            if not pKp > 0.0:
                return None
            a = rz / pKp
            x += a * p
            r -= a * Kp
            z = self.solver.solve(r)
            rz_new = float(r @ z)
            if rz_new <= stop:
                self.n_cg += 1
                return x
            # at the rate so far it would not get there in time: factorise now, not later
            ratio = rz_new / rz0
            if ratio >= 1.0 or k * np.log(stop / rz0) / np.log(ratio) > max_iter:
                return None
            p = z + (rz_new / rz) * p
            rz = rz_new
        return None

    # -- the solve ----------------------------------------------------------------------------

    def solve(self, g: Array, u0: Array | None = None, deadline: float | None = None) -> NewtonResult:
        """Equilibrium under nodal forces g (forces on fixed nodes are ignored).

        `deadline` (a time.perf_counter() value): the solve begins no Newton iteration that
        would end past it, judged by the longest of its latest timed iterations
        (:meth:`iteration_estimate`), nor its start's factorisation once past it, and stops
        unconverged with status time_limit, so a frame's time budget holds inside a hard solve
        (seconds on the liver), not only between solves.
        Shape: g (n, 3), u0 (n, 3) or None (rest) -> result.u (n, 3).
        """
        t0 = time.perf_counter()
        asm, opt = self.asm, self.options
        g = np.asarray(g, np.float64)
        x = np.zeros(asm.n_free) if u0 is None else asm.pack(u0).astype(np.float64)
        target = asm.pack(g)
        if not (np.isfinite(target).all() and np.isfinite(x).all()):
            return self._result(x, False, "non_finite", 0, 0, [], t0)

        u_start = asm.unpack(x)
        if not np.isfinite(asm.energy(u_start)):
            return self._result(x, False, "non_finite", 0, 0, [], t0)
        f0 = asm.pack(asm.internal_force(u_start))
        measure = functools.partial(self.relative_residual, target=target, f0=f0)
        if not np.any(target - f0):
            return self._result(x, True, "converged", 0, 0, [0.0], t0)
        # relative to the load, not to the increment from a warm start (which can be tiny)
        with np.errstate(over="ignore"):  # an absurd load's norm overflows: its solve stops at its first step
            ref = float(max(np.linalg.norm(target), np.linalg.norm(target - f0)))
        if ref == 0.0:
            return self._result(x, True, "converged", 0, 0, [0.0], t0)

        # the predictor's factor, also the preconditioner of the Newton steps: the tangent at
        # the start, reused when the held factor was made exactly there (a registration's
        # adjoint leaves it so); made here otherwise, so that the result is a function of
        # (g, u0) alone, whatever the solver did before
        if self._factor_x is not None and np.array_equal(self._factor_x, x):
            shifts = 0
        elif deadline is not None and time.perf_counter() > deadline:  # no factorisation past it (the liver's: ~1 s)
            return self._result(x, False, "time_limit", 0, 0, [], t0)
        else:
            shifts = self._factor_tangent(asm.tangent(u_start), x)
        s, ds, iterations, steps = 0.0, 1.0, 0, 0
        self._cg_skip = self._cg_backoff = 0  # per solve, so that u is a function of (g, u0)
        residuals: list[float] = []
        have_factor = True
        status = "converged"
        while s < 1.0:
            if deadline is not None and time.perf_counter() > deadline:
                status = "time_limit"
                break
            # tangent predictor along the load path, with the step cut so that it asks no
            # element for more than `step_strain` of |grad du|
            x_try = x
            if have_factor:
                dx = self.solver.solve(target - f0)
                grad = asm.F(asm.unpack(dx)) - np.eye(3)
                with np.errstate(over="ignore"):  # an absurd load's strains overflow: inf stops it below
                    gmax = float(np.sqrt((grad**2).sum(axis=(1, 2)).max()))
                ds = min(ds, opt.step_strain / gmax) if gmax > 0 else ds
                if not ds >= opt.min_load_step:  # strains of thousands asked for (or inf): no path
                    status = "load_step_too_small"
                    break
            s_try = min(1.0, s + ds)
            load = f0 + s_try * (target - f0)
            if have_factor:
                x_pred = x + (s_try - s) * dx
                if np.isfinite(asm.energy(asm.unpack(x_pred))):
                    x_try = x_pred
            tol = opt.rtol if s_try == 1.0 else max(opt.rtol, opt.step_rtol)
            budget = min(opt.max_step_iter, opt.max_iter - iterations)
            atol = max(tol * ref, self.roundoff)
            x_new, ok, its, hist, nshift, factored, why = self._newton(x_try, load, atol, ref, budget, deadline)
            iterations += its
            shifts += nshift
            residuals += hist
            have_factor = have_factor or factored
            if ok:
                x, s, steps = x_new, s_try, steps + 1
                if its <= 4:
                    ds = min(2.0 * ds, 1.0)
                continue
            if why == "time_limit":
                status = why
                break
            if iterations >= opt.max_iter:
                status = "max_iter"
                x = x_new if _is_better(hist) else x
                break
            ds *= 0.5
            if ds < opt.min_load_step:
                status = "load_step_too_small" if why != "non_finite" else why
                break
        converged = status == "converged"
        if not converged:
            log.info(
                "Newton stopped: %s after %d iterations (residual %.2e)",
                status,
                iterations,
                residuals[-1] if residuals else np.nan,
            )
        unmeasured = converged or status == "time_limit"  # a time_limit's pass would overrun its deadline
        res = self._result(x, converged, status, iterations, steps, residuals, t0, None if unmeasured else measure)
        res.solver = self.solver if have_factor else None
        res.shifted = shifts
        return res

    def _newton(self, x: Array, load: Array, atol: float, ref: float, budget: int, deadline: float | None = None):
        """Newton iterations at a fixed load, until `deadline` at most. Returns (x, ok,
        iterations, history, shifts, factored, reason)."""
        asm, opt = self.asm, self.options
        hist: list[float] = []
        shifts = 0
        factored = False
        u = asm.unpack(x)
        Pi = asm.energy(u) - float(load @ x)
        t_it = None  # when the iteration under way began
        for it in range(budget + 1):
            r = asm.pack(asm.internal_force(u)) - load
            rn = float(np.linalg.norm(r))
            if t_it is not None:  # an iteration ends with its successor's residual
                self.iteration_seconds.append(time.perf_counter() - t_it)
            hist.append(rn / ref)
            if not np.isfinite(rn):
                return x, False, it, hist, shifts, factored, "non_finite"
            if rn <= atol:
                return x, True, it, hist, shifts, factored, "converged"
            # roundoff floor: within 100x of the tolerance, a Newton step that no longer halves
            # the residual cannot do better (the internal forces cancel to that precision)
            if it >= 2 and rn <= 100.0 * atol and rn > 0.5 * hist[-2] * ref:
                return x, True, it, hist, shifts, factored, "converged"
            if it == budget:
                break
            t_it = time.perf_counter()
            if deadline is not None and t_it + self.iteration_estimate() > deadline:
                self._forget_slowest()
                return x, False, it, hist, shifts, factored, "time_limit"
            K = asm.tangent(u)
            # inexact Newton: the step to a relative accuracy eta, by conjugate gradients on
            # the held factor when they get there quickly, else from a new factorisation.
            # eta shrinks with the residual (superlinear convergence) but never below what
            # reaching atol needs
            eta = max(min(CG_FORCING, np.sqrt(rn / ref)), 1e-3 * atol / rn)
            dx = None
            if self._cg_skip > 0:  # they failed lately: the tangent moves fast here
                self._cg_skip -= 1
            else:
                dx = self.solve_tangent(K, -r, eta)
                # back off after a failure (skip 1, 2, 4, 8 steps), try every step after a success
                self._cg_backoff = 0 if dx is not None else min(max(2 * self._cg_backoff, 1), 8)
                self._cg_skip = self._cg_backoff
            if dx is None:
                shifts += self._factor_tangent(K, x)
                factored = True
                dx = -self.solver.solve(r)
            slope = float(r @ dx)  # < 0: descent (K positive definite)
            alpha = 1.0
            for _ in range(opt.max_halvings):
                x_new = x + alpha * dx
                u_new = asm.unpack(x_new)
                Pi_new = asm.energy(u_new) - float(load @ x_new)
                if np.isfinite(Pi_new):
                    # roundoff: near the solution Pi cannot resolve the decrease any more
                    lost = abs(slope) * alpha < 1e-13 * max(abs(Pi), 1e-300)
                    if Pi_new <= Pi + opt.armijo * alpha * slope or lost:
                        break
                alpha *= 0.5
            else:
                return x, False, it + 1, hist, shifts, factored, "line_search"
            x, u, Pi = x_new, u_new, Pi_new
        return x, False, budget, hist, shifts, factored, "max_iter"

    def _forget_slowest(self) -> None:
        """Drop the time that just refused an iteration: a refusing solve times nothing, so one
        stall (a GC pause, a page-in) would otherwise refuse every later solve whose budget is
        under it. A true slowness comes back with the next iteration that runs."""
        if self.iteration_seconds:
            self.iteration_seconds.remove(max(self.iteration_seconds))

    def iteration_estimate(self) -> float:
        """Seconds the next Newton iteration is expected to take: the longest of the latest
        timed (a factorising one takes several times a conjugate-gradient one), 0 before any."""
        return max(self.iteration_seconds, default=0.0)

    def relative_residual(self, x: Array, target: Array, f0: Array) -> float | None:
        """||f_int(x) - target|| / max(||target||, ||target - f0||) over free dofs x (the solve's
        rtol norm, f0 its start's internal force); None where it is not finite. Every vector is
        scaled by the largest entry first, so an absurd load's norms do not overflow."""
        with np.errstate(over="ignore", invalid="ignore"):
            r = self.asm.pack(self.asm.internal_force(self.asm.unpack(x))) - target
            if not np.isfinite(r).all():
                return None
            scale = float(max(np.abs(r).max(), np.abs(target).max(), np.abs(target - f0).max()))
            if scale == 0.0:
                return 0.0
            ref = max(np.linalg.norm(target / scale), np.linalg.norm((target - f0) / scale))
            rel = float(np.linalg.norm(r / scale) / ref)
        return rel if np.isfinite(rel) else None

    def _result(self, x, converged, status, iterations, steps, residuals, t0, measure=None) -> NewtonResult:
        return NewtonResult(
            u=self.asm.unpack(x),
            converged=converged,
            status=status,
            iterations=iterations,
            load_steps=steps,
            residuals=residuals,
            seconds=time.perf_counter() - t0,
            measure=None if measure is None else functools.partial(measure, x),
        )


def _is_better(hist: list[float]) -> bool:
    return len(hist) > 1 and np.isfinite(hist[-1]) and hist[-1] < hist[0]


def _diagonal_slots(K: sp.csr_matrix) -> Array:
    """Index into K.data of each diagonal entry (the pattern must hold the whole diagonal)."""
    rows = np.repeat(np.arange(K.shape[0]), np.diff(K.indptr))
    slots = np.flatnonzero(rows == K.indices)
    if slots.size != K.shape[0]:
        raise ValueError("the stiffness pattern lacks some diagonal entries")
    return slots

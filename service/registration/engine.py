"""One frame's registration: min over support forces g of J(u_g) + alpha/2 |g|^2 with L-BFGS-B.

The engine sees a forward operator (network or FEM, :mod:`.forward`) and a point-to-surface
distance; it never knows which method it drives. Each frame:

1. evaluates the rest state g = 0: its gradient is the reference for the relative tolerance
   (how hard the cloud pulls on the undeformed organ, independent of where the frame starts,
   so a warm start that begins near the optimum stops early), and a cloud already on the rest
   surface ends the frame at once; a warm network frame evaluates it on a spare core beside
   step 2 (:mod:`.spare`), on a distance of its own that only ever sees the rest surface;
2. evaluates the warm start g0 (and any fallback starts; the lowest wins) and whitens the
   variables there (:mod:`.precondition`) with the curvature the stream carries, or, if asked
   and none applies, a damped Gauss-Newton model: L-BFGS-B then runs in variables where the
   curvature is about the identity and the first unit step is a (quasi-)Newton step;
3. runs L-BFGS-B (SciPy) with exact gradients (the forward model's adjoint) and keeps the best
   iterate it saw, whatever stops it; or, asked for and where the model offers its Jacobian
   (the reduced network), Levenberg-Marquardt (:mod:`.levenberg`), which re-linearises at
   every step instead of learning the curvature one gradient at a time (unbounded only).

Scaling also keeps SciPy's stopping tests meaningful: J is about 1e-6 m^2 on a liver, and its
tests are absolute below 1.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import time
from collections.abc import Callable

import numpy as np
from scipy.optimize import minimize

from ..forward import ForwardFailed, ForwardOperator
from ..spare import Beside
from .distance import NonFinitePositions, PointToSurface
from .levenberg import GaussNewtonModel, KrylovGaussNewton, distance_gram, prepare
from .precondition import Curvature, gauss_newton
from .settings import DEFAULT_ALPHA, DEFAULT_GTOL, NAMES, OPTIMIZERS, Optimizer, SessionConfig

log = logging.getLogger(__name__)

Array = np.ndarray


@dataclasses.dataclass(frozen=True)
class SolveOptions:
    """How one frame is solved. A session's settings of the same name pass through
    (:meth:`of`); the rest are the engine's own."""

    alpha: float = DEFAULT_ALPHA  # regularisation weight on |g|^2 (m^2 / N^2, with J in m^2)
    gtol: float = DEFAULT_GTOL["fem"]
    max_iter: int = 100
    force_bound: float | None = None  # |g_i| <= bound per component, newtons
    force_scale: float = 0.1  # N: the optimiser's unit when the model gives no Jacobian
    precondition: bool = False  # damped Gauss-Newton preconditioning from the rest Jacobian
    # (precondition.py) where no carried curvature applies: a third of the beam's iterations
    # from rest; on the liver's partial clouds it costs time and force accuracy, so opt-in
    max_evaluations: int | None = None  # default: 3 x max_iter
    max_failures: int = 4  # forward failures at trial points before the frame gives up
    time_budget: float | None = None  # seconds: past it the frame returns its best iterate
    # (status time_limit); a display wants a frame in time more than a last digit. A session
    # passes solve_frame a deadline inside it that leaves room for the frame's outputs
    optimizer: Optimizer = SessionConfig.optimizer  # or "levenberg-marquardt" (levenberg.py): no
    # bounds, and a model with a Jacobian (the reduced network); for whole-surface cold starts
    damping: float = 0.1  # Levenberg-Marquardt's first damping, in units of the mean curvature
    # the model sees (the beam: 0.1 lands every case at the L-BFGS-B error; 0.01 lands some in
    # a wrong basin from rest, 0.22 against 0.11 mm mean TRE)

    @classmethod
    def of(cls, config: SessionConfig) -> SolveOptions:
        """The options a session's settings give (per-model defaults already filled in)."""
        given = {f.name: getattr(config, f.name) for f in dataclasses.fields(cls) if f.name in NAMES}
        budget = config.time_budget_ms
        return cls(**given, time_budget=None if budget is None else 1e-3 * budget)


_BOUNDED = "levenberg-marquardt takes no force bounds: use optimizer 'lbfgsb'"
_NO_JACOBIAN = (
    "levenberg-marquardt needs a forward model with a Jacobian: the fem method, or the network method "
    "with a reduced surrogate (a Jacobian in its basis); use optimizer 'lbfgsb'"
)


def check_optimizer(op: ForwardOperator, options: SolveOptions) -> None:
    """Refuse, saying why, an optimizer this operator and these options cannot run (a session
    checks once, when it opens; solve_frame refuses the same at first use), and ready what it
    will run (Levenberg-Marquardt's compiled kernel), so that no frame's clock pays for it."""
    if options.optimizer not in OPTIMIZERS:
        raise ValueError(f"optimizer must be one of {list(OPTIMIZERS)}, got {options.optimizer!r}")
    _refuse_bounds(options)
    if options.optimizer == "levenberg-marquardt":
        _jacobian(op, np.zeros((len(op.support), 3)))
        prepare()  # its compiled kernel, before any frame's clock runs


def _refuse_bounds(options: SolveOptions) -> None:
    """Levenberg-Marquardt takes no force bounds: refused by a session when it opens and by
    solve_frame before any evaluation."""
    if options.optimizer == "levenberg-marquardt" and options.force_bound is not None:
        raise ValueError(_BOUNDED)


def _jacobian(op, g: Array):
    """The operator's Jacobian at g (levenberg.py's model input); ValueError if it has none."""
    jacobian = getattr(op, "jacobian", None)
    jac = None if jacobian is None else jacobian(g)
    if jac is None:
        raise ValueError(_NO_JACOBIAN)
    return jac


@dataclasses.dataclass
class Timing:
    forward: float = 0.0
    distance: float = 0.0
    gradient: float = 0.0
    total: float = 0.0
    beside: float = 0.0  # the rest state's evaluation on a spare core, overlapping the rest

    def as_ms(self) -> dict[str, float]:
        d = {
            "forward": 1e3 * self.forward,
            "distance": 1e3 * self.distance,
            "gradient": 1e3 * self.gradient,
            "total": 1e3 * self.total,
            "beside": 1e3 * self.beside,
        }  # by hand: dataclasses.asdict costs 10 us a frame
        d["optimizer"] = max(0.0, d["total"] - d["forward"] - d["distance"] - d["gradient"])
        return d


@dataclasses.dataclass
class FrameSolution:
    """The best iterate of one frame and how the optimiser got there. Shape: g (k, 3)."""

    g: Array
    objective: float  # J at g (m^2), without the regularisation
    value: float  # J + alpha/2 |g|^2
    rms: float  # RMS distance of all the cloud's points to the surface at g (m)
    converged: bool
    status: str  # converged | max_iter | time_limit | line_search | forward_failed | non_finite | stalled
    iterations: int
    evaluations: int
    timing: Timing
    message: str = ""
    u: Array | None = None  # (p, 3) the displacement of op.nodes at g, where g was evaluated here


class _Stop(Exception):
    def __init__(self, status: str, message: str) -> None:
        self.status, self.message = status, message
        self.iterations: int | None = None  # the optimiser's, where it knows them


def _forward_stop(exc: ForwardFailed) -> _Stop:
    """The frame's stop for a forward model's failure: time_limit where a solve gave up at the
    frame's deadline (the FEM's, see solve_frame), else forward_failed."""
    return _Stop("time_limit" if exc.status == "time_limit" else "forward_failed", str(exc))


class _Done(Exception):
    """Nothing to optimise: the rest state is the answer, for the reason given."""

    def __init__(self, message: str) -> None:
        self.message = message


class Objective:
    """Phi(g) = J(x0 + u_g) + alpha/2 |g|^2 and its gradient (the adjoint), timed, with the
    best iterate remembered. Shape: g (k, 3); x0 (p, 3) rest positions of `op.nodes`."""

    def __init__(
        self, op: ForwardOperator, distance, rest_positions: Array, alpha: float, timing: Timing | None = None
    ):
        self.op, self.distance, self.rest, self.alpha = op, distance, rest_positions, float(alpha)
        self.timing = timing or Timing()
        self.evaluations = 0
        self.timed = 0  # evaluations made here (not a rest state recorded from beside), as timed
        self.best_value, self.best_g, self.best_J = math.inf, None, math.inf
        self.best_u: Array | None = None  # displacement of op.nodes at best_g
        self.best_rms = self.rest_rms = math.nan  # at the best iterate, and at g = 0
        self.last_u: Array | None = None  # displacement of op.nodes at the last evaluation
        self.rest_u: Array | None = None  # ... and at g = 0
        self.prefetch: Callable[[Array], None] | None = None  # told each loaded g the model answered

    def __call__(self, g: Array) -> tuple[float, Array, float]:
        """(Phi, dPhi/dg (k, 3), J). Raises _Stop when the forward model fails or a value is
        not finite."""
        self.evaluations += 1
        self.timed += 1
        t0 = time.perf_counter()
        try:
            u, pullback = self.op(g)
        except ForwardFailed as exc:
            self.timing.forward += time.perf_counter() - t0
            raise _forward_stop(exc) from None
        t1 = time.perf_counter()
        self.last_u = u
        flat = g.ravel()
        g2 = float(flat @ flat)  # |g|^2: one BLAS call, where np.sum(g * g) or np.any(g) cost 15 us
        if self.prefetch is not None and g2 > 0.0:
            self.prefetch(g)
        try:
            J, dJ_dx = self.distance(self.rest + u)
        except NonFinitePositions:
            self.timing.forward += t1 - t0
            raise _not_finite() from None
        if g2 == 0.0:
            self.rest_u, self.rest_rms = u, self.distance.last_rms
        t2 = time.perf_counter()
        grad = pullback(dJ_dx, rows=self.distance.gradient_nodes) + self.alpha * g
        t3 = time.perf_counter()
        self.timing.forward += t1 - t0
        self.timing.distance += t2 - t1
        self.timing.gradient += t3 - t2
        value = J + 0.5 * self.alpha * g2
        if not (math.isfinite(value) and _finite(grad)):
            raise _not_finite("the objective or its gradient")
        if value < self.best_value:
            self.best_value, self.best_g, self.best_J = value, np.array(g, np.float64), J
            self.best_u = u
            self.best_rms = self.distance.last_rms
        return value, grad, J

    def late(self, deadline: float | None) -> bool:
        """Whether an evaluation begun now would end past `deadline` (None: never), judged by
        the mean time of this frame's evaluations so far: the optimiser does not begin one that
        would overrun the frame's budget."""
        if deadline is None:
            return False
        t = self.timing
        mean = (t.forward + t.distance + t.gradient) / self.timed if self.timed else 0.0
        return time.perf_counter() + mean > deadline

    def record_rest(self, J: float, grad: Array, u: Array, rms: float, seconds: float) -> tuple[float, Array]:
        """Counts a rest-state evaluation made elsewhere (:func:`_rest_state`) as this one's own,
        after the frame's other starts: (Phi, dPhi/dg) at g = 0, best if no start was lower."""
        self.evaluations += 1
        self.timing.beside += seconds
        self.rest_u, self.rest_rms = u, rms
        if not (math.isfinite(J) and _finite(grad)):
            raise _Stop("non_finite", "the objective or its gradient is not finite")
        if J <= self.best_value:  # ties to rest, as when it is evaluated first
            self.best_value, self.best_g, self.best_J, self.best_rms = J, np.zeros_like(grad), J, rms
            self.best_u = u
        return J, grad


def _finite(a: Array) -> bool:
    """Whether every entry is finite. A NaN or an infinity makes the sum so, so a finite sum
    settles it in one reduction; only a sum that overflowed looks at the entries."""
    return math.isfinite(np.add.reduce(a, axis=None)) or bool(np.isfinite(a).all())


class ScalarScaling:
    """The fallback when a model offers no Jacobian: g = s z, objective / F."""

    def __init__(self, force_scale: float, value_scale: float) -> None:
        self.s, self.value_scale = force_scale, value_scale

    def to_g(self, z: Array) -> Array:
        return self.s * z

    def to_z(self, g: Array) -> Array:
        return g / self.s

    def grad_z(self, grad_g: Array) -> Array:
        return grad_g * (self.s / self.value_scale)


def _gauss_newton(op, distance: PointToSurface, rest: Array, u: Array, grad: Array, alpha: float):
    """The damped Gauss-Newton preconditioner at the frame's start (None if the model offers
    no low-rank Jacobian)."""
    low_rank = getattr(op, "low_rank_jacobian", None)
    jac = low_rank() if low_rank is not None else None
    if jac is None:
        return None
    U, Q = jac
    x = rest + u
    c = distance.closest(x)
    faces = distance.faces[c.face]
    tri = x[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    P = gauss_newton(U, Q, faces, c.bary, n, alpha, c.kept.astype(np.float64))  # trimmed points weigh 0
    P.set_step(grad.ravel())
    return P


def solve_frame(
    op: ForwardOperator,
    distance: PointToSurface,
    rest_positions: Array,
    g0: Array,
    options: SolveOptions = SolveOptions(),
    curvature: Curvature | None = None,
    fallbacks: tuple[Array, ...] = (),
    rest_distance: PointToSurface | None = None,
    prefetch: Callable[[Array], None] | None = None,
    deadline: float | None = None,
) -> FrameSolution:
    """Register one frame.

    `distance(x)` returns J and dJ/dx for positions x (p, 3) of `op.nodes` (rest positions
    `rest_positions` (p, 3) plus displacement). Shape: g0 (k, 3) the starting forces.
    `curvature`, carried by a stream from frame to frame, preconditions unbounded solves and
    learns from this one. `fallbacks` are other starting forces (k, 3) worth one evaluation
    each (a stream's last converged forces); the frame starts from the lowest objective among
    them, g0 and zero, skipping any whose forward solve fails. `rest_distance`, the same
    distance bound to the same cloud but evaluated only at rest, lets an operator with
    ``at_rest()`` (the network) evaluate a warm frame's rest state beside its start (spare.py).
    `prefetch(g)` is told every loaded point as soon as the forward model has answered there,
    before its distance: a session may start the frame's outputs for it on a spare core.
    `deadline` (a time.perf_counter() value), where given, stops the optimiser in place of
    `options.time_budget` counted from here: a session sets it so that the outputs it computes
    after the solve fit in its budget too. The rest state and the starts are evaluated whatever
    the deadline (the FEM's solves among them stop at it); the optimiser begins no evaluation
    that would end past it (by the frame's mean evaluation so far) and stops with status
    time_limit.
    """
    _refuse_bounds(options)  # the Jacobian, Levenberg-Marquardt's other need, at its first use
    t_start = time.perf_counter()
    at_rest = getattr(op, "at_rest", None)
    beside = None
    if rest_distance is not None and at_rest is not None and any(np.any(s) for s in (g0, *fallbacks)):  # warm
        beside = Beside(functools.partial(_rest_state, at_rest, rest_distance, rest_positions))
    timing = Timing()
    k = len(op.support)
    evaluate = Objective(op, distance, rest_positions, options.alpha, timing)
    evaluate.best_g = np.asarray(g0, np.float64).copy()
    max_eval = options.max_evaluations or 3 * options.max_iter
    if deadline is None and options.time_budget is not None:
        deadline = t_start + options.time_budget

    # an operator with slow solves (the FEM) stops inside one at the deadline, not after it
    timed_op = deadline is not None and hasattr(op, "deadline")
    status, message, nit = "converged", "", 0
    try:
        if timed_op:
            op.deadline = deadline
        # the rest state: the objective's scale, the gradient reference, the trivial answer; a
        # warm frame's is evaluated beside its start's, on a spare core where there is one
        zero = np.zeros((k, 3))
        if beside is None:
            v_rest, grad_rest, _ = evaluate(zero)
            _check_rest(v_rest, rest_positions)
            best = _best_start(evaluate, (g0, *fallbacks), options)
        else:
            try:
                best = _best_start(evaluate, (g0, *fallbacks), options)
            finally:  # never leave the job running on the session's rest distance
                rest = beside.result()
            v_rest, grad_rest = evaluate.record_rest(*rest)
            _check_rest(v_rest, rest_positions)
        # the start: the lowest of the warm start, the fallbacks and the rest state (ties to
        # rest), so a start that a bad frame left far off costs one evaluation, not the frame
        if best is None or v_rest <= best.value:
            best = _Start(zero, v_rest, grad_rest, evaluate.rest_u)
        # the stopping test, in force space whatever variables the optimiser runs in
        g_tol = options.gtol * float(np.abs(grad_rest).max())
        if g_tol == 0.0:  # no force on the support moves what the points match (a cloud off a held face)
            raise _Done(
                f"no force on the support moves the surface the points match: the rest state stands "
                f"({evaluate.rest_rms:.3g} m rms from the cloud)"
            )
        _check_alpha(options.alpha, v_rest, grad_rest, best.value)
        # the optimiser's trial points only: the starts' share the spare core with the rest state
        evaluate.prefetch = prefetch
        if options.optimizer == "levenberg-marquardt":
            status, message, nit = _levenberg_marquardt(
                op, distance, evaluate, best, g_tol, options, max_eval, deadline
            )
        else:
            status, message, nit = _lbfgsb(
                op, distance, evaluate, best, v_rest, g_tol, options, curvature, max_eval, deadline
            )
    except _Done as done:
        status, message = "converged", done.message
        evaluate.best_g, evaluate.best_value, evaluate.best_J = np.zeros((k, 3)), v_rest, v_rest
        evaluate.best_u = evaluate.rest_u
        evaluate.best_rms = evaluate.rest_rms
    except _Stop as stop:
        status, message = stop.status, stop.message
        nit = stop.iterations if stop.iterations is not None else nit
    finally:
        if timed_op:
            op.deadline = None  # the session's outputs are computed after the frame, in full

    timing.total = time.perf_counter() - t_start
    return FrameSolution(
        g=evaluate.best_g,
        objective=float(evaluate.best_J),
        value=float(evaluate.best_value),
        rms=float(evaluate.best_rms),
        converged=status == "converged",
        status=status,
        iterations=nit,
        evaluations=evaluate.evaluations,
        timing=timing,
        message=message,
        u=evaluate.best_u,
    )


@dataclasses.dataclass(frozen=True)
class _Start:
    """Where a frame's optimiser begins: forces (k, 3), Phi, its gradient (k, 3), and the
    displacement (p, 3) of the operator's nodes there."""

    g: Array
    value: float
    grad: Array
    u: Array

    @property
    def cold(self) -> bool:
        """Whether the frame starts at rest (g = 0): far from its optimum, as no stream led it."""
        return not np.any(self.g)


def _check_rest(v_rest: float, rest_positions: Array) -> None:
    """Ends the frame (_Done) where the cloud lies on the rest surface."""
    # coordinates first: NumPy reduces a (p, 3) array along its long axis 9x slower
    size = float(np.linalg.norm(np.ptp(np.ascontiguousarray(rest_positions.T), axis=1))) or 1.0
    if v_rest <= 0.5 * (1e-9 * size) ** 2:
        raise _Done("the cloud lies on the rest surface: no force needed")


def _check_alpha(alpha: float, v_rest: float, grad_rest: Array, v_best: float) -> None:
    """Ends the frame (_Done) where alpha is so large that no force lowers the objective by what
    the optimiser resolves: Phi(g) >= Phi(0) + grad.g + alpha/2 |g|^2 (J's curvature is no
    less than 0 near g = 0, and alpha's swamps it), whose least value is |grad|^2 / (2 alpha)
    below the rest state's; the regularised answer, |grad| / alpha in force, is the rest state.
    L-BFGS-B would stall at it ("relative reduction"), saying nothing of alpha."""
    gain = _roundoff_gain(alpha, grad_rest, v_rest)
    if gain is not None and v_best >= v_rest - gain:
        raise _Done(
            f"alpha {alpha:.3g} is so large that no force can lower the objective measurably (by "
            f"{gain:.3g} m^2 at most, from {v_rest:.3g} m^2 at rest): the rest state stands"
        )


#: the relative decrease of the (scaled) objective below which L-BFGS-B stops ("relative
#: reduction"): the finest change it resolves, a few units in the last place of a double
_FTOL = 1e-15


def _roundoff_gain(alpha: float, grad: Array, value: float) -> float | None:
    """The most any force lowers Phi below `value`, its value at a point of gradient `grad`
    (force space): |grad|^2 / (2 alpha), the least of Phi's lower bound there (_check_alpha),
    where that is under _FTOL of `value`, the finest change the optimiser resolves (the point
    is Phi's optimum up to roundoff); None where there is more to gain."""
    flat = grad.ravel()
    gain = float(flat @ flat) / (2.0 * alpha)
    return gain if gain <= _FTOL * abs(value) else None


def _stall(alpha: float, grad: Array, value: float, message: str) -> tuple[str, str]:
    """(status, message) of an optimiser stopped for want of a measurable decrease at a point of
    objective `value` and gradient `grad`: converged where no force can lower Phi measurably
    from there (_roundoff_gain), its optimum up to roundoff (alpha swamps the gradient test's
    scale there), the message saying so; else stalled, with the optimiser's `message`."""
    gain = _roundoff_gain(alpha, grad, value)
    if gain is None:
        return "stalled", message
    return "converged", (
        f"the objective stopped decreasing at working precision where no force can lower it by "
        f"more than {gain:.3g} m^2 (under {_FTOL:g} of its {value:.3g} m^2): its optimum for "
        f"alpha {alpha:.3g} up to roundoff"
    )


def _best_start(evaluate: Objective, candidates: tuple[Array, ...], options: SolveOptions) -> _Start | None:
    """The lowest of the candidate starts (the first of equals), each evaluated once; None if
    none is non-zero or none could be evaluated."""
    bounded = options.force_bound is not None
    best: _Start | None = None
    tried: list[Array] = []
    for cand in candidates:
        cand = np.asarray(cand, np.float64)
        if bounded:
            cand = np.clip(cand, -options.force_bound, options.force_bound)
        if not np.any(cand) or any(np.array_equal(cand, t) for t in tried):
            continue  # rest is the engine's own candidate
        tried.append(cand)
        try:
            v, grad, _ = evaluate(cand)
        except _Stop as stop:
            if stop.status == "time_limit":
                raise
            continue  # a start the forward model cannot reach is no start; the others stand
        if best is None or v < best.value:
            best = _Start(cand, v, grad, evaluate.last_u)
    return best


def _rest_state(at_rest, distance: PointToSurface, rest_positions: Array) -> tuple[float, Array, Array, float, float]:
    """The rest state on `distance` (bound to the frame's cloud, evaluated only at rest): J,
    its gradient, u, the RMS distance and the seconds it took. Touches nothing of the frame's."""
    t0 = time.perf_counter()
    u, pullback = at_rest()
    try:
        J, dJ_dx = distance(rest_positions + u)
    except NonFinitePositions:
        raise _not_finite() from None
    grad = pullback(dJ_dx, rows=distance.gradient_nodes)
    return J, grad, u, distance.last_rms, time.perf_counter() - t0


def _lbfgsb(
    op,
    distance: PointToSurface,
    evaluate: Objective,
    begin: _Start,
    v_rest: float,
    g_tol: float,
    options: SolveOptions,
    curvature: Curvature | None,
    max_eval: int,
    deadline: float | None,
) -> tuple[str, str, int]:
    """SciPy's L-BFGS-B from `begin` in whitened variables (the module docstring, step 2-3),
    stopped by the force-space gradient test. (status, message, iterations)."""
    k = len(op.support)
    bounded = options.force_bound is not None
    P = None
    if curvature is not None and not bounded and not begin.cold:
        # the carried curvature models the Hessian near the last frames' optima: from the
        # rest state it misleads (cold starts on the paper's liver: 12 % converged with
        # it, 100 % without)
        P = curvature.preconditioner(begin.grad.ravel())
    if P is None and options.precondition and not bounded:
        P = _gauss_newton(op, distance, evaluate.rest, begin.u, begin.grad, options.alpha)
    if P is None:
        P = ScalarScaling(options.force_scale, v_rest if v_rest > 0 else 1.0)
    # whitening amplifies the gradient along weakly seen directions, so the stopping test
    # (g_tol) stays in force space
    lo = -options.force_bound if bounded else -np.inf
    hi = options.force_bound if bounded else np.inf
    z0 = P.to_z(begin.g.ravel())
    cache = {"z": z0, "out": (begin.value / P.value_scale, P.grad_z(begin.grad.ravel()))}

    best = {"z": z0, "f": cache["out"][0], "grad": begin.grad.ravel()}
    failures = []

    def fun(z: Array) -> tuple[float, Array]:
        if np.array_equal(z, cache["z"]):
            return cache["out"]
        if evaluate.evaluations >= max_eval:
            raise _Stop("max_iter", "evaluation budget spent")
        if evaluate.late(deadline):
            raise _Stop("time_limit", _spent(options))
        g = P.to_g(z)
        try:
            value, grad, _ = evaluate(g.reshape(k, 3))
        except _Stop as stop:
            if stop.status != "forward_failed" or len(failures) >= options.max_failures:
                raise
            # a trial point the forward model cannot reach: a steep bowl around the best
            # point, so the line search reads it as an overshoot and shortens the step
            failures.append(stop.message)
            w = 10.0 * (1.0 + abs(best["f"]))
            dz = z - best["z"]
            return best["f"] + w * float(dz @ dz) + w, 2.0 * w * dz
        f, gz = value / P.value_scale, P.grad_z(grad.ravel())
        if f < best["f"]:
            best.update(z=z.copy(), f=f, grad=grad.ravel())
        last.update(z=z, g=g, grad=grad.ravel())
        return f, gz

    last = {"z": z0, "g": begin.g.ravel(), "grad": begin.grad.ravel()}
    path_g, path_grad = [last["g"]], [last["grad"]]  # accepted iterates: curvature pairs

    def converged(intermediate_result) -> None:
        """Projected gradient in force space against gtol x the rest state's."""
        if not np.array_equal(intermediate_result.x, last["z"]):
            return
        g, grad = last["g"], last["grad"]
        path_g.append(g)
        path_grad.append(grad)
        if bounded:
            grad = np.where(grad > 0, np.minimum(grad, g - lo), np.maximum(grad, g - hi))
        if np.abs(grad).max() <= g_tol:
            raise StopIteration

    bounds = None
    if bounded:
        b = P.to_z(np.full(3 * k, float(options.force_bound)))
        bounds = list(zip(-b, b, strict=True))
    try:
        res = minimize(
            fun, z0, jac=True, method="L-BFGS-B", bounds=bounds, callback=converged,
            options={"maxiter": options.max_iter, "gtol": 0.0, "ftol": _FTOL, "maxcor": 20, "maxls": 30},
        )  # fmt: skip
    except _Stop as stop:  # a limit or a failure between iterations: the accepted ones so far
        stop.iterations = len(path_g) - 1
        raise
    nit, status = int(res.nit), _status(res)
    message = _MESSAGES.get(status, "{nit} iterations").format(nit=nit, scipy=res.message)
    if curvature is not None and not bounded and status == "converged":
        curvature.update(path_g, path_grad)  # only converged frames teach the carried curvature
    # after the curvature: steps at roundoff's scale teach it nothing
    if status == "stalled":
        status, message = _stall(options.alpha, best["grad"], best["f"] * P.value_scale, message)
    if failures and status != "converged":
        status, message = "forward_failed", f"{len(failures)} trial points failed: {failures[-1]}"
    return status, message, nit


def _levenberg_marquardt(
    op,
    distance: PointToSurface,
    evaluate: Objective,
    begin: _Start,
    g_tol: float,
    options: SolveOptions,
    max_eval: int,
    deadline: float | None,
) -> tuple[str, str, int]:
    """Damped Gauss-Newton steps (levenberg.py) from `begin`, Nielsen's damping update (faster
    from rest, see _COLD_SHRINK); the objective only decreases, so the current point is the
    best. (status, message, iterations)."""
    k = len(op.support)
    g, f, grad = begin.g.ravel(), begin.value, begin.grad.ravel()
    x = evaluate.rest + begin.u
    match = distance.last_match
    if match is None or not np.array_equal(match.x, x):  # the start was not the last evaluation
        distance(x)
        match = distance.last_match
    mu, mu_min, nu, nit, failures = None, 0.0, 2.0, 0, []
    cold = begin.cold
    readout = getattr(op, "readout", None)
    while np.abs(grad).max() > g_tol:
        if nit >= options.max_iter:
            return "max_iter", f"{nit} iterations", nit
        if evaluate.late(deadline):  # before the FEM's 3k solves
            return "time_limit", _spent(options), nit
        # the distance's curvature through a constant readout (the network's) needs no Jacobian:
        # a spare core forms it while this one forms the Jacobian
        gram = None if readout is None else Beside(functools.partial(distance_gram, readout, match, distance.faces))
        model = _model(op, g.reshape(k, 3), match, distance.faces, grad, options.alpha, gram, nit)
        if mu is None:
            mu = options.damping * model.scale
            mu_min = _MIN_DAMPING * model.scale
        for _ in range(_MAX_REJECTIONS + 1):
            if evaluate.evaluations >= max_eval:
                return "max_iter", "evaluation budget spent", nit
            if evaluate.late(deadline):
                return "time_limit", _spent(options), nit
            d = _step(model, mu, nit)
            if d is None:  # the held Jacobian no longer preconditions: form this g's own
                model = _model(op, g.reshape(k, 3), match, distance.faces, grad, options.alpha, gram, nit, exact=True)
                d = _step(model, mu, nit)
                assert d is not None  # a Jacobian's own model always steps
            if not np.abs(d).max() > 1e-12 * max(float(np.abs(g).max()), _TINY):
                return *_stall(options.alpha, grad, f, "the damped step vanished before the gradient test"), nit
            try:
                fn, gn, _ = evaluate((g + d).reshape(k, 3))
            except _Stop as stop:
                if stop.status != "forward_failed" or len(failures) >= options.max_failures:
                    stop.iterations = nit
                    raise
                failures.append(stop.message)  # a trial the model cannot reach: damp harder
                mu, nu = mu * nu, 2.0 * nu
                continue
            if fn < f:
                rho = min((f - fn) / max(model.predicted(d, mu), _TINY), 1.0)
                g, f, grad, match = g + d, fn, gn.ravel(), distance.last_match
                shrink = max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                if cold and rho > _TRUSTED_GAIN:  # far from the optimum: trust the model
                    shrink = _COLD_SHRINK
                mu = max(mu * shrink, mu_min)
                nu, nit = 2.0, nit + 1
                break
            mu, nu = mu * nu, 2.0 * nu
        else:
            no_decrease = f"no decrease in {_MAX_REJECTIONS + 1} damped steps: the objective's precision"
            return *_stall(options.alpha, grad, f, no_decrease), nit
    return "converged", "projected gradient below gtol", nit


def _model(op, g: Array, match, faces: Array, grad: Array, alpha: float, gram, nit: int, exact: bool = False):
    """The damped Gauss-Newton model at g: through products with the Jacobian where the
    operator offers them (the FEM once it has formed one: a few solves a step, not 3k), else
    through the Jacobian itself (the FEM solves only where g was not its last evaluation)."""
    try:
        products = None if exact else getattr(op, "jacobian_products", lambda g: None)(g)
        if products is not None:
            return KrylovGaussNewton(products, match, faces, grad, alpha)
        jac = _jacobian(op, g)
    except ForwardFailed as exc:
        raise _stopped(exc, nit) from None
    A = None if gram is None else gram.result()[1]
    return GaussNewtonModel(jac, match, faces, grad, alpha, A)


def _step(model, mu: float, nit: int) -> Array | None:
    """model.step(mu), a forward failure inside it (the products' solves) a stop."""
    try:
        return model.step(mu)
    except ForwardFailed as exc:
        raise _stopped(exc, nit) from None


def _stopped(exc: ForwardFailed, nit: int) -> _Stop:
    stop = _forward_stop(exc)
    stop.iterations = nit
    return stop


def _not_finite(what: str = "the forward model's displacement") -> _Stop:
    """A frame's stop where a value is not finite: its result says so (status non_finite)."""
    return _Stop("non_finite", f"{what} is not finite")


def _spent(options: SolveOptions) -> str:
    """The message of a frame stopped by its time budget (or a deadline its session set)."""
    if options.time_budget is None:
        return "deadline reached"
    return f"time budget of {1e3 * options.time_budget:g} ms spent"


#: Rejected steps in a row before Levenberg-Marquardt stops: past them (damping x 2^28) what is
#: left to gain is below the float32 network's noise (docs/performance.md, "Constants")
_MAX_REJECTIONS = 6

#: The least damping, in units of the frame's first Gauss-Newton model's mean curvature: it keeps
#: directions the distance hardly sees from drifting on noise (docs/performance.md, "Constants")
_MIN_DAMPING = 3e-4

#: From rest, a step whose gain ratio exceeds _TRUSTED_GAIN cuts the damping by _COLD_SHRINK, not
#: Nielsen's 1/3: cold starts trust their model, warm starts keep Nielsen's rule (docs/performance.md)
_TRUSTED_GAIN = 0.9
_COLD_SHRINK = 0.2


_TINY = np.finfo(np.float64).tiny


#: a stop's message in the API's words (SciPy's own in parentheses where it says more)
_MESSAGES = {
    "converged": "projected gradient below gtol",
    "max_iter": "{nit} iterations",
    "stalled": "the objective stopped decreasing at working precision before the gradient test (L-BFGS-B: {scipy})",
    "line_search": "the line search found no lower point along the step (L-BFGS-B: {scipy})",
}


def _status(res) -> str:
    """Why SciPy's L-BFGS-B stopped, in the API's words."""
    msg = str(res.message).upper()
    if "CALLBACK" in msg or "STOPITERATION" in msg or "PROJECTED GRADIENT" in msg:
        return "converged"  # our force-space gradient test (or SciPy's own) was met
    if "RELATIVE REDUCTION" in msg:
        return "stalled"  # no further decrease at working precision before the gradient test
    if "ITERATIONS REACHED" in msg or "EVALUATIONS" in msg:
        return "max_iter"
    if "ABNORMAL" in msg or "LINE SEARCH" in msg or "LNSRCH" in msg:
        return "line_search"
    return "converged" if res.success else "stalled"

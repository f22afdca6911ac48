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
3. runs L-BFGS-B (SciPy, :mod:`.drive_lbfgsb`) with exact gradients (the forward model's
   adjoint) and keeps the best iterate it saw, whatever stops it; or, asked for and where the
   model offers its Jacobian (the reduced network), Levenberg-Marquardt (:mod:`.drive_levenberg`,
   its step :mod:`.levenberg`), which re-linearises at every step instead of learning the
   curvature one gradient at a time (unbounded only).

Scaling also keeps SciPy's stopping tests meaningful: J is about 1e-6 m^2 on a liver, and its
tests are absolute below 1.

This module holds the frame's course (steps 1-2, the trivial answers, the hand-over to a
driver); the objective is :mod:`.objective`, the options :mod:`.options`, and how a frame ends
early :mod:`.stops`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable

import numpy as np

from ..forward import ForwardOperator
from ..spare import Beside
from .distance import PointToSurface
from .drive_lbfgsb import lbfgsb
from .drive_levenberg import levenberg_marquardt
from .objective import Objective, Start, Timing, rest_state
from .options import SolveOptions, check_optimizer, refuse_bounds
from .precondition import Curvature
from .reach import Box, answer_past_reach
from .stops import Done, Stop, roundoff_gain

#: a cloud this near its rest surface (rms, a share of the organ's size: 10 nm on a 10 cm organ)
#: is at rest; below it L-BFGS-B only chases rounding (a <f4 cloud stalled after 132 evaluations)
REST_RMS = 1e-7
_F32_EPS = float(np.finfo(np.float32).eps)

#: what callers import from here (session.py, the tests): the frame's own names and the re-exported ones
__all__ = ["FAILED", "FrameSolution", "Objective", "SolveOptions", "Timing", "check_optimizer", "solve_frame"]

#: statuses whose frame leaves the warm start as it was (too_far: its answer says nothing of the cloud)
FAILED = ("forward_failed", "non_finite", "too_far")

Array = np.ndarray


@dataclasses.dataclass
class FrameSolution:
    """The best iterate of one frame and how the optimiser got there. Shape: g (k, 3)."""

    g: Array
    objective: float  # J at g (m^2), without the regularisation
    value: float  # J + alpha/2 |g|^2
    rms: float  # RMS distance of all the cloud's points to the surface at g (m)
    converged: bool
    status: str  # converged | max_iter | time_limit | line_search | forward_failed | non_finite | stalled | too_far
    iterations: int
    evaluations: int
    timing: Timing
    message: str = ""
    u: Array | None = None  # (p, 3) the displacement of op.nodes at g, where g was evaluated here


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
    box: Box | None = None,
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
    `box`, the model's rest bounding box (reach.py), is what the reach is judged against, as a
    session's check judges the cloud; without one, the box of `rest_positions` (the matching
    surface's nodes: a patch's box is smaller than the organ's, so a caller matching a patch
    passes the model's, as a session does).
    """
    refuse_bounds(options)
    # a direct caller's (30 us-1 ms a frame); a session passes the model's, made when it opens
    box = Box(rest_positions) if box is None else box
    t_start = time.perf_counter()
    at_rest = getattr(op, "at_rest", None)
    beside = None
    if rest_distance is not None and at_rest is not None and any(np.any(s) for s in (g0, *fallbacks)):  # warm
        beside = Beside(functools.partial(rest_state, at_rest, rest_distance, rest_positions))
    timing = Timing()
    k = len(op.support)
    evaluate = Objective(op, distance, rest_positions, options.alpha, timing)
    evaluate.best_g = np.asarray(g0, np.float64).copy()
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
            _check_rest(evaluate.rest_rms, rest_positions)
            best = _best_start(evaluate, (g0, *fallbacks), options)
        else:
            try:
                best = _best_start(evaluate, (g0, *fallbacks), options)
            finally:  # never leave the job running on the session's rest distance
                rest = beside.result()
            v_rest, grad_rest = evaluate.record_rest(*rest)
            _check_rest(evaluate.rest_rms, rest_positions)
        # the start: the lowest of the warm start, the fallbacks and the rest state (ties to
        # rest), so a start that a bad frame left far off costs one evaluation, not the frame
        if best is None or v_rest <= best.value:
            best = Start(zero, v_rest, grad_rest, evaluate.rest_u)
        # the stopping test, in force space whatever variables the optimiser runs in
        g_tol = options.gtol * float(np.abs(grad_rest).max())
        if g_tol == 0.0:  # no force on the support moves what the points match (a cloud off a held face)
            if np.any(grad_rest):  # the tolerance underflowed: the test would pass anything
                raise Stop("stalled", f"the rest gradient ({np.abs(grad_rest).max():.3g}) is below what gtol resolves")
            raise Done(_still_at_rest(evaluate, options.alpha))
        _check_alpha(options.alpha, v_rest, grad_rest, best.value, distance, evaluate.rest_rms)
        # the optimiser's trial points only: the starts' share the spare core with the rest state
        evaluate.prefetch = prefetch
        # the optimiser's own evaluations: the rest state's and the starts' pay for no line search
        max_eval = evaluate.evaluations + (options.max_evaluations or 3 * options.max_iter)
        if options.optimizer == "levenberg-marquardt":
            status, message, nit = levenberg_marquardt(op, distance, evaluate, best, g_tol, options, max_eval, deadline)
        else:
            status, message, nit = lbfgsb(
                op, distance, evaluate, best, v_rest, g_tol, options, curvature, max_eval, deadline
            )
    except Done as done:  # the rest state is the answer, if the cloud is near enough to say so (_judge)
        status, message = "converged", done.message
        evaluate.best_g, evaluate.best_value, evaluate.best_J = np.zeros((k, 3)), v_rest, v_rest
        evaluate.best_u = evaluate.rest_u
        evaluate.best_rms = evaluate.rest_rms
    except Stop as stop:
        status, message = stop.status, stop.message
        nit = stop.iterations if stop.iterations is not None else nit
    finally:
        if timed_op:
            op.deadline = None  # the session's outputs are computed after the frame, in full

    status, message = _judge(status, message, evaluate, rest_positions, box)
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


def _check_rest(rest_rms: float, rest_positions: Array) -> None:
    """Ends the frame (Done) where the cloud lies on the rest surface, by distance (a huber
    loss's tiny threshold makes its value tiny far off): within REST_RMS of the organ's size,
    or of a float32 cloud's rounding (API.md takes <f4 points) where the mesh sits off the origin."""
    # coordinates first: NumPy reduces a (p, 3) array along its long axis 9x slower
    rest = np.ascontiguousarray(rest_positions.T)
    size = float(np.linalg.norm(np.ptp(rest, axis=1))) or 1.0
    if rest_rms <= REST_RMS * size + _F32_EPS * float(np.abs(rest).max()):
        raise Done("the cloud lies on the rest surface: no force needed")


def _judge(status: str, message: str, evaluate: Objective, rest_positions: Array, box: Box) -> tuple[str, str]:
    """The frame's status given its answer (the best iterate): one whose distance is not finite,
    or past the reach (reach.answer_past_reach: points 1e20 m off made the rest state look like an
    optimum), is never converged and, failed, never moves the warm start. A frame that evaluated
    nothing (a deadline in its rest state's solve) keeps its own status."""
    rms = evaluate.best_rms
    if status in FAILED or (math.isnan(rms) and status != "converged"):
        return status, message
    if not math.isfinite(rms):  # API.md: never converged
        return "non_finite", f"the distance at the answer is not finite ({message})"
    u = evaluate.best_u

    def distances() -> Array:  # at the answer, searched for only where its rms leaves the reach open
        return evaluate.distance.closest(rest_positions if u is None else rest_positions + u).distance

    far = answer_past_reach(box, rms, distances)
    return ("too_far", f"{far} ({message})") if far else (status, message)


def _still_at_rest(evaluate: Objective, alpha: float) -> str:
    """Why the rest gradient is exactly zero: no force on the support moves the matched surface
    (a cloud off a held face), or the points' pull underflowed in it (a huber threshold of
    1e-300 scales the loss's linear part, so alpha swamps it; the squared loss moved the
    surface). Told apart by pulling back the pull scaled to its largest entry: one more rest
    pullback, on this rare path alone."""
    stands = f"the rest state stands ({evaluate.rest_rms:.3g} m rms from the cloud)"
    distance, op = evaluate.distance, evaluate.op
    u = evaluate.rest_u
    _, pull = distance(evaluate.rest if u is None else evaluate.rest + u)
    scale = float(np.abs(pull).max())
    if scale > 0.0:
        at_rest = getattr(op, "at_rest", None)  # the network's records nothing on the operator
        _, pullback = at_rest() if at_rest is not None else op(np.zeros((len(op.support), 3)))
        if np.any(pullback(pull / scale, rows=distance.gradient_nodes)):
            why = _huber_pull(distance) if distance.loss == "huber" else "the loss's pull"
            return (
                f"alpha {alpha:.3g} swamps {why}: its gradient at rest vanishes and no force can lower "
                f"the objective measurably: {stands}"
            )
    return f"no force on the support moves the surface the points match: {stands}"


def _check_alpha(
    alpha: float, v_rest: float, grad_rest: Array, v_best: float, distance: PointToSurface, rest_rms: float
) -> None:
    """Ends the frame (Done) where alpha is so large that no force lowers the objective by what
    the optimiser resolves: Phi(g) >= Phi(0) + grad.g + alpha/2 |g|^2 (J's curvature is no
    less than 0 near g = 0, and alpha's swamps it), whose least value is |grad|^2 / (2 alpha)
    below the rest state's; the regularised answer, |grad| / alpha in force, is the rest state.
    L-BFGS-B would stall at it ("relative reduction"), saying nothing of alpha. The message
    names a huber threshold too where it is what shrank the pull (_threshold_swamped)."""
    gain = roundoff_gain(alpha, grad_rest, v_rest)
    if gain is not None and v_best >= v_rest - gain:
        by = f"by {gain:.3g} m^2 at most, from {v_rest:.3g} m^2 at rest"
        if _threshold_swamped(alpha, grad_rest, distance, rest_rms):
            raise Done(
                f"alpha {alpha:.3g} swamps {_huber_pull(distance)} (the cloud is {rest_rms:.3g} m rms from rest): "
                f"no force can lower the objective measurably ({by}): the rest state stands"
            )
        raise Done(
            f"alpha {alpha:.3g} is so large that no force can lower the objective measurably ({by}): "
            "the rest state stands"
        )


def _huber_pull(distance: PointToSurface) -> str:
    return f"the huber loss's pull, which scales with its threshold loss_param {distance.delta:.3g} m"


def _threshold_swamped(alpha: float, grad_rest: Array, distance: PointToSurface, rest_rms: float) -> bool:
    """Whether a huber threshold under the cloud's distance is what makes its pull too small to
    lower the objective: a point past it pulls delta / d of the squared loss's, so with the
    threshold at the points' distance (rms / delta more pull, J at rms^2 / 2) some force would
    (roundoff_gain). An estimate, on this rare path only; scaled first, as 1e-300's pull underflows."""
    if distance.loss != "huber" or distance.delta is None or not distance.delta < rest_rms:
        return False
    with np.errstate(over="ignore", invalid="ignore"):
        grad = grad_rest * (rest_rms / distance.delta)
    return not np.isfinite(grad).all() or roundoff_gain(alpha, grad, 0.5 * rest_rms**2) is None


def _best_start(evaluate: Objective, candidates: tuple[Array, ...], options: SolveOptions) -> Start | None:
    """The lowest of the candidate starts (the first of equals), each evaluated once; None if
    none is non-zero or none could be evaluated."""
    bounded = options.force_bound is not None
    best: Start | None = None
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
        except Stop as stop:
            if stop.status == "time_limit":
                raise
            continue  # a start the forward model cannot reach is no start; the others stand
        if best is None or v < best.value:
            best = Start(cand, v, grad, evaluate.last_u)
    return best

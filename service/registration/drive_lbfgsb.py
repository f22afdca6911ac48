"""The L-BFGS-B driver (SciPy): one frame's optimiser run from its start in whitened variables
(:mod:`.precondition`: the curvature the stream carries, or a damped Gauss-Newton model, else a
scalar unit), with exact gradients, stopped by a gradient test in force space; it reads SciPy's
reasons to stop in the API's words."""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize

from .distance import PointToSurface
from .objective import Objective, Start
from .options import SolveOptions
from .precondition import Curvature, gauss_newton
from .stops import FTOL, Stop, spent, stall

Array = np.ndarray


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


def lbfgsb(
    op,
    distance: PointToSurface,
    evaluate: Objective,
    begin: Start,
    v_rest: float,
    g_tol: float,
    options: SolveOptions,
    curvature: Curvature | None,
    max_eval: int,
    deadline: float | None,
) -> tuple[str, str, int]:
    """SciPy's L-BFGS-B from `begin` in whitened variables (engine.py's docstring, steps 2-3),
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
    # SciPy's stopping tests are relative to |f|: where far points hold a share no force
    # changes (huber, PointToSurface.far_share) it sees the decrease from the start, which that
    # share cannot hide; other losses see Phi itself (ref 0.0: the same bits as before)
    ref = begin.value if distance.far_share else 0.0
    cache = {"z": z0, "out": ((begin.value - ref) / P.value_scale, P.grad_z(begin.grad.ravel()))}

    best = {"z": z0, "f": cache["out"][0], "grad": begin.grad.ravel()}
    failures = []

    def fun(z: Array) -> tuple[float, Array]:
        if np.array_equal(z, cache["z"]):
            return cache["out"]
        if evaluate.evaluations >= max_eval:
            raise Stop("max_iter", "evaluation budget spent")
        if evaluate.late(deadline):
            raise Stop("time_limit", spent(options))
        g = P.to_g(z)
        try:
            value, grad, _ = evaluate(g.reshape(k, 3))
        except Stop as stop:
            if stop.status != "forward_failed" or len(failures) >= options.max_failures:
                raise
            # a trial point the forward model cannot reach: a steep bowl around the best
            # point, so the line search reads it as an overshoot and shortens the step
            failures.append(stop.message)
            w = 10.0 * (1.0 + abs(best["f"] + ref / P.value_scale))
            dz = z - best["z"]
            return best["f"] + w * float(dz @ dz) + w, 2.0 * w * dz
        f, gz = (value - ref) / P.value_scale, P.grad_z(grad.ravel())
        if f < best["f"]:
            best.update(z=z.copy(), f=f, grad=grad.ravel())
        last.update(z=z, g=g, grad=grad.ravel())
        return f, gz

    last = {"z": z0, "g": begin.g.ravel(), "grad": begin.grad.ravel()}
    path_g, path_grad = [last["g"]], [last["grad"]]  # accepted iterates: curvature pairs

    def projected(g: Array, grad: Array) -> float:
        """The largest component of the projected gradient in force space (a bound's outward
        pull left out)."""
        if bounded:
            grad = np.where(grad > 0, np.minimum(grad, g - lo), np.maximum(grad, g - hi))
        return float(np.abs(grad).max())

    def converged(intermediate_result) -> None:
        """Projected gradient in force space against gtol x the rest state's."""
        if not np.array_equal(intermediate_result.x, last["z"]):
            return
        g, grad = last["g"], last["grad"]
        path_g.append(g)
        path_grad.append(grad)
        if projected(g, grad) <= g_tol:
            raise StopIteration

    bounds = None
    if bounded:
        b = P.to_z(np.full(3 * k, float(options.force_bound)))
        bounds = list(zip(-b, b, strict=True))
    try:
        res = minimize(
            fun, z0, jac=True, method="L-BFGS-B", bounds=bounds, callback=converged,
            options={"maxiter": options.max_iter, "gtol": 0.0, "ftol": FTOL, "maxcor": 20, "maxls": 30},
        )  # fmt: skip
    except Stop as stop:  # a limit or a failure between iterations: the accepted ones so far
        stop.iterations = len(path_g) - 1
        raise
    nit, status = int(res.nit), _status(res)
    message = _MESSAGES.get(status, "{nit} iterations").format(nit=nit, scipy=res.message)
    if curvature is not None and not bounded and status == "converged":
        curvature.update(path_g, path_grad)  # only converged frames teach the carried curvature
    # after the curvature: steps at roundoff's scale teach it nothing
    if status == "stalled":
        status, message = stall(options.alpha, best["grad"], best["f"] * P.value_scale + ref, message)
    if status == "stalled":  # how far the gradient test was, in the message
        ratio = projected(P.to_g(best["z"]), best["grad"]) / g_tol
        message = _STALLED.format(ratio=ratio, scipy=res.message)
    if failures and status != "converged":
        status, message = "forward_failed", f"{len(failures)} trial points failed: {failures[-1]}"
    return status, message, nit


#: a stop's message in the API's words (SciPy's own in parentheses where it says more)
_MESSAGES = {
    "converged": "projected gradient below gtol",
    "max_iter": "{nit} iterations",
    "line_search": "the line search found no lower point along the step (L-BFGS-B: {scipy})",
}
#: a stall's: no step lowers Phi, yet its gradient is not small (at a kink of the network's
#: piecewise-linear activations the slope jumps, and no gradient vanishes at the optimum)
_STALLED = (
    "the objective stopped decreasing at working precision with its gradient still {ratio:.3g} times the "
    "tolerance: no step lowers it, yet the gradient test does not pass (as on a kink, where the network's "
    "piecewise-linear activations make the slope jump) (L-BFGS-B: {scipy})"
)


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

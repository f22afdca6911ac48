"""The Levenberg-Marquardt driver: damped Gauss-Newton steps (the step itself: :mod:`.levenberg`)
from a frame's start, Nielsen's damping update with a faster cut from rest, re-linearised at
every accepted step; unbounded only, through the model's Jacobian or its products."""

from __future__ import annotations

import functools

import numpy as np

from ..forward import ForwardFailed
from ..spare import Beside
from .distance import PointToSurface
from .levenberg import GaussNewtonModel, KrylovGaussNewton, distance_gram
from .objective import Objective, Start
from .options import SolveOptions, jacobian_of
from .stops import Stop, spent, stall, stopped

Array = np.ndarray


def levenberg_marquardt(
    op,
    distance: PointToSurface,
    evaluate: Objective,
    begin: Start,
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
            return "time_limit", spent(options), nit
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
                return "time_limit", spent(options), nit
            d = _step(model, mu, nit)
            if d is None:  # the held Jacobian no longer preconditions: form this g's own
                model = _model(op, g.reshape(k, 3), match, distance.faces, grad, options.alpha, gram, nit, exact=True)
                d = _step(model, mu, nit)
                assert d is not None  # a Jacobian's own model always steps
            if not np.abs(d).max() > 1e-12 * max(float(np.abs(g).max()), _TINY):
                return *stall(options.alpha, grad, f, "the damped step vanished before the gradient test"), nit
            try:
                fn, gn, _ = evaluate((g + d).reshape(k, 3))
            except Stop as stop:
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
            return *stall(options.alpha, grad, f, no_decrease), nit
    return "converged", "projected gradient below gtol", nit


def _model(op, g: Array, match, faces: Array, grad: Array, alpha: float, gram, nit: int, exact: bool = False):
    """The damped Gauss-Newton model at g: through products with the Jacobian where the
    operator offers them (the FEM once it has formed one: a few solves a step, not 3k), else
    through the Jacobian itself (the FEM solves only where g was not its last evaluation)."""
    try:
        products = None if exact else getattr(op, "jacobian_products", lambda g: None)(g)
        if products is not None:
            return KrylovGaussNewton(products, match, faces, grad, alpha)
        jac = jacobian_of(op, g)
    except ForwardFailed as exc:
        raise stopped(exc, nit) from None
    A = None if gram is None else gram.result()[1]
    return GaussNewtonModel(jac, match, faces, grad, alpha, A)


def _step(model, mu: float, nit: int) -> Array | None:
    """model.step(mu), a forward failure inside it (the products' solves) a stop."""
    try:
        return model.step(mu)
    except ForwardFailed as exc:
        raise stopped(exc, nit) from None


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

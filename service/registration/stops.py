"""How a frame ends short of its optimiser's own end: the exceptions that carry a stop or a
trivial answer out of the objective and the drivers to solve_frame, their messages in the API's
words, and the test that tells an optimum reached up to roundoff from a stall."""

from __future__ import annotations

import numpy as np

from ..forward import ForwardFailed
from .options import SolveOptions

Array = np.ndarray


class Stop(Exception):
    def __init__(self, status: str, message: str) -> None:
        self.status, self.message = status, message
        self.iterations: int | None = None  # the optimiser's, where it knows them


def forward_stop(exc: ForwardFailed) -> Stop:
    """The frame's stop for a forward model's failure: time_limit where a solve gave up at the
    frame's deadline (the FEM's, see solve_frame), else forward_failed."""
    return Stop("time_limit" if exc.status == "time_limit" else "forward_failed", str(exc))


def stopped(exc: ForwardFailed, nit: int) -> Stop:
    stop = forward_stop(exc)
    stop.iterations = nit
    return stop


def not_finite(what: str = "the forward model's displacement") -> Stop:
    """A frame's stop where a value is not finite: its result says so (status non_finite)."""
    return Stop("non_finite", f"{what} is not finite")


def spent(options: SolveOptions) -> str:
    """The message of a frame stopped by its time budget (or a deadline its session set)."""
    if options.time_budget is None:
        return "deadline reached"
    return f"time budget of {1e3 * options.time_budget:g} ms spent"


class Done(Exception):
    """Nothing to optimise: the rest state is the answer, for the reason given."""

    def __init__(self, message: str) -> None:
        self.message = message


#: the relative decrease of the (scaled) objective below which L-BFGS-B stops ("relative
#: reduction"): the finest change it resolves, a few units in the last place of a double
FTOL = 1e-15


def roundoff_gain(alpha: float, grad: Array, value: float) -> float | None:
    """The most any force lowers Phi below `value`, its value at a point of gradient `grad`
    (force space): |grad|^2 / (2 alpha), the least of Phi's lower bound there (the engine's
    _check_alpha), where that is under FTOL of `value`, the finest change the optimiser
    resolves (the point is Phi's optimum up to roundoff); None where there is more to gain."""
    flat = grad.ravel()
    gain = float(flat @ flat) / (2.0 * alpha)
    return gain if gain <= FTOL * abs(value) else None


def stall(alpha: float, grad: Array, value: float, message: str) -> tuple[str, str]:
    """(status, message) of an optimiser stopped for want of a measurable decrease at a point of
    objective `value` and gradient `grad`: converged where no force can lower Phi measurably
    from there (roundoff_gain), its optimum up to roundoff (alpha swamps the gradient test's
    scale there), the message saying so; else stalled, with the optimiser's `message`."""
    gain = roundoff_gain(alpha, grad, value)
    if gain is None:
        return "stalled", message
    return "converged", (
        f"the objective stopped decreasing at working precision where no force can lower it by "
        f"more than {gain:.3g} m^2 (under {FTOL:g} of its {value:.3g} m^2): its optimum for "
        f"alpha {alpha:.3g} up to roundoff"
    )

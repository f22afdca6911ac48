"""The frame's objective Phi(g) = J(x0 + u_g) + alpha/2 |g|^2 and its gradient (the forward
model's adjoint), timed, with the best iterate remembered; the points the optimisers begin from
(:class:`Start`); and the rest state evaluated elsewhere (a spare core, :func:`rest_state`)."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable

import numpy as np

from ..forward import ForwardFailed, ForwardOperator
from .distance import NonFinitePositions, PointToSurface
from .stops import Stop, forward_stop, not_finite

Array = np.ndarray


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
        # an operator that keeps its solves (the FEM's) holds the best one however many follow
        self._pin: Callable[[Array], None] | None = getattr(op, "pin", None)

    def __call__(self, g: Array) -> tuple[float, Array, float]:
        """(Phi, dPhi/dg (k, 3), J). Raises Stop when the forward model fails or a value is
        not finite."""
        self.evaluations += 1
        self.timed += 1
        t0 = time.perf_counter()
        try:
            u, pullback = self.op(g)
        except ForwardFailed as exc:
            self.timing.forward += time.perf_counter() - t0
            raise forward_stop(exc) from None
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
            raise not_finite() from None
        if g2 == 0.0:
            self.rest_u, self.rest_rms = u, self.distance.last_rms
        t2 = time.perf_counter()
        grad = pullback(dJ_dx, rows=self.distance.gradient_nodes) + self.alpha * g
        t3 = time.perf_counter()
        self.timing.forward += t1 - t0
        self.timing.distance += t2 - t1
        self.timing.gradient += t3 - t2
        value = J + 0.5 * self.alpha * g2
        if not (math.isfinite(value) and finite(grad)):
            raise not_finite("the objective or its gradient")
        if value < self.best_value:
            self.best_value, self.best_g, self.best_J = value, np.array(g, np.float64), J
            self.best_u = u
            self.best_rms = self.distance.last_rms
            if self._pin is not None and g2 > 0.0:  # zero load is the rest state, never solved
                self._pin(g)
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
        """Counts a rest-state evaluation made elsewhere (:func:`rest_state`) as this one's own,
        after the frame's other starts: (Phi, dPhi/dg) at g = 0, best if no start was lower."""
        self.evaluations += 1
        self.timing.beside += seconds
        self.rest_u, self.rest_rms = u, rms
        if not (math.isfinite(J) and finite(grad)):
            raise Stop("non_finite", "the objective or its gradient is not finite")
        if J <= self.best_value:  # ties to rest, as when it is evaluated first
            self.best_value, self.best_g, self.best_J, self.best_rms = J, np.zeros_like(grad), J, rms
            self.best_u = u
        return J, grad


def finite(a: Array) -> bool:
    """Whether every entry is finite. A NaN or an infinity makes the sum so, so a finite sum
    settles it in one reduction; only a sum that overflowed looks at the entries."""
    return math.isfinite(np.add.reduce(a, axis=None)) or bool(np.isfinite(a).all())


@dataclasses.dataclass(frozen=True)
class Start:
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


def rest_state(at_rest, distance: PointToSurface, rest_positions: Array) -> tuple[float, Array, Array, float, float]:
    """The rest state on `distance` (bound to the frame's cloud, evaluated only at rest): J,
    its gradient, u, the RMS distance and the seconds it took. Touches nothing of the frame's."""
    t0 = time.perf_counter()
    u, pullback = at_rest()
    try:
        J, dJ_dx = distance(rest_positions + u)
    except NonFinitePositions:
        raise not_finite() from None
    grad = pullback(dJ_dx, rows=distance.gradient_nodes)
    return J, grad, u, distance.last_rms, time.perf_counter() - t0

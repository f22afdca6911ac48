"""How far from its model a cloud may lie and still be registered.

A deformed organ's surface stays within about one size of its rest bounding box, so a cloud far
past that is not the organ: most often one in the wrong unit (millimetres against a model in
metres lies hundreds of sizes off), or an unaligned camera frame. Far enough off, the distance's
gradient is lost to rounding (every closest point ties at 1e16 sizes) and the rest state looked
like an optimum. A session refuses (:func:`check_reach`, a ValueError: a 422) a cloud whose
median point lies past REACH sizes (a unit mistake), and one with any point past FAR sizes (no
depth camera's stray point lies there; 199 of 400 points at 1e20 m leave the median near, and
drown the gradient), and one of at least SPAN_POINTS points that spans less than SPAN of the
model's size (a cloud in metres against a model in millimetres, near its origin, lies inside its
box). Stray points nearer than FAR are a depth camera's outliers, for the robust
losses; the engine never calls an answer converged whose median point lies past the reach from
its surface, or whose rms distance lies past FAR (:func:`answer_past_reach`).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

Array = np.ndarray

#: how many model sizes (its rest bounding box's diagonal) from that box a cloud's median point
#: may lie, and from an answer's surface: 10x leaves room for any deformation and catches a
#: millimetre cloud (~500 sizes off)
REACH = 10.0
#: how many model sizes from that box any one point may lie, and an answer's rms distance: 200 m
#: for a 20 cm liver, past any depth camera's range, and far below where rounding ties every
#: closest point (1e16 sizes)
FAR = 1000.0

#: the least share of the model's size that a cloud of SPAN_POINTS or more may span (its bounding
#: box's diagonal): a depth camera's partial view spans a few percent of an organ at least, and a
#: cloud in metres against a model in millimetres a thousandth; 1/200 lies between, 5x from each
SPAN = 1 / 200
#: the fewest points whose span is judged: one point spans nothing, and two or three (markers) tell no unit
SPAN_POINTS = 4


class Box:
    """A model's rest bounding box and its size (the diagonal, m). Shape: nodes (n, 3)."""

    def __init__(self, nodes: Array) -> None:
        self.lo, self.hi = nodes.min(axis=0), nodes.max(axis=0)
        self.size = float(np.linalg.norm(self.hi - self.lo)) or 1.0

    def offsets(self, points: Array) -> Array:
        """Each point's (m, 3) distance from the box (0 inside), (m,)."""
        # per coordinate, how far past the nearer face (zero inside): whole-array, no loop over points
        gap = np.maximum(np.maximum(self.lo - points, points - self.hi), 0.0)
        with np.errstate(over="ignore"):
            d = np.sqrt(np.einsum("ij,ij->i", gap, gap))
            over = np.isinf(d)  # squares past a double (points at 1e300): those few again without squares
            if over.any():
                d[over] = np.hypot.reduce(gap[over], axis=1)  # inf only past a double's range itself
        return d

    def within(self, distance: float) -> bool:
        """Whether a (finite) distance from the box is within the reach."""
        return math.isfinite(distance) and distance <= REACH * self.size


def _amount(x: float, unit: str = "") -> str:
    """A figure for a message: 3 digits, or where it is not finite, what that means."""
    return f"{x:.3g}{unit}" if math.isfinite(x) else "beyond float range"


def check_reach(box: Box, points: Array) -> None:
    """ValueError, in one line, where the cloud's median point lies farther than REACH model
    sizes from the model's box (naming the likely unit mistake), any point farther than FAR
    (naming how many and how far), or a cloud of SPAN_POINTS or more spans less than SPAN of
    the model's size (naming the other unit mistake)."""
    offsets = box.offsets(points)
    median = float(np.median(offsets))
    if not box.within(median):
        raise ValueError(
            f"points lie too far from the model: the median point is {_amount(median, ' m')} from its bounding box, "
            f"{_amount(median / box.size)} times its size of {box.size:.3g} m (at most {REACH:g}); points are in "
            f"the mesh's frame and unit (metres): is the cloud in millimetres, or not aligned with the model?"
        )
    bound = FAR * box.size
    far = offsets > bound
    if far.any():
        farthest = float(offsets.max())
        raise ValueError(
            f"points lie too far from the model: {int(far.sum())} of {len(points)} points are more than "
            f"{bound:.3g} m ({FAR:g} times its size of {box.size:.3g} m) from its bounding box, the farthest "
            f"{_amount(farthest, ' m')}; no depth camera sees that far: drop them, or is the cloud not in metres?"
        )
    span = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    if len(points) >= SPAN_POINTS and span < SPAN * box.size:
        raise ValueError(
            f"points lie too close together for the model: the cloud spans {span:.3g} (its bounding box's "
            f"diagonal), {span / box.size:.3g} of the model's size of {box.size:.3g} (at least {SPAN:g}); points "
            f"are in the mesh's unit: is the cloud in metres while the model is in millimetres?"
        )


def answer_past_reach(box: Box, rms: float, distances: Callable[[], Array]) -> str:
    """Why an answer lies too far from its cloud for a registration ("" where it does not), by
    its finite `rms` distance and `distances()`, the (m,) point-to-surface distances at it: its
    median point past REACH sizes (which a few strays cannot move, and which a rest answer of a
    cloud past the reach fails: the rest surface lies in its box), or its rms past FAR sizes
    (199 of 400 points at 1e20 m leave the median near)."""
    if rms > FAR * box.size:
        return (
            f"the answer lies {rms:.3g} m rms from the cloud, {rms / box.size:.3g} times the model's size "
            f"(at most {FAR:g}): too far for a registration"
        )
    # half the points lie at the median or past it, so it is at most sqrt(2) rms: no search needed
    if math.sqrt(2.0) * rms <= REACH * box.size:
        return ""
    median = float(np.median(distances()))
    if box.within(median):
        return ""
    return (
        f"the answer's median point lies {median:.3g} m from its surface, {median / box.size:.3g} times the "
        f"model's size (at most {REACH:g}): too far for a registration"
    )

"""How far from its model a cloud may lie and still be registered.

A deformed organ's surface stays within about one size of its rest bounding box, so a cloud far
past that is not the organ: most often one in the wrong unit (millimetres against a model in
metres lies hundreds of sizes off), or an unaligned camera frame. Far enough off, the distance's
gradient is lost to rounding (every closest point ties at 1e16 sizes) and the rest state looked
like an optimum. A session refuses such a cloud (:func:`check_reach`, a ValueError: a 422); the
engine never calls a frame converged whose rest state lies past the reach (:func:`within`).
A few stray points far off are a depth camera's outliers, for the robust losses: the test reads
the median point.
"""

from __future__ import annotations

import math

import numpy as np

Array = np.ndarray

#: how many model sizes (its rest bounding box's diagonal) from that box a cloud's median point
#: may lie: 10x leaves room for any deformation and catches a millimetre cloud (~500 sizes off)
REACH = 10.0


class Box:
    """A model's rest bounding box and its size (the diagonal, m). Shape: nodes (n, 3)."""

    def __init__(self, nodes: Array) -> None:
        self.lo, self.hi = nodes.min(axis=0), nodes.max(axis=0)
        self.size = float(np.linalg.norm(self.hi - self.lo)) or 1.0

    def median_offset(self, points: Array) -> float:
        """The median over the points (m, 3) of their distance from the box (0 inside)."""
        # per coordinate, how far past the nearer face (zero inside): whole-array, no loop over points
        gap = np.maximum(np.maximum(self.lo - points, points - self.hi), 0.0)
        return float(np.median(np.sqrt(np.einsum("ij,ij->i", gap, gap))))

    def within(self, distance: float) -> bool:
        """Whether a (finite) distance from the box is within the reach."""
        return math.isfinite(distance) and distance <= REACH * self.size


def check_reach(box: Box, points: Array) -> None:
    """ValueError, in one line that names the likely unit mistake, where the cloud's median
    point lies farther than REACH model sizes from the model's box."""
    offset = box.median_offset(points)
    if box.within(offset):
        return
    raise ValueError(
        f"points lie too far from the model: the median point is {offset:.3g} m from its bounding box, "
        f"{offset / box.size:.3g} times its size of {box.size:.3g} m (at most {REACH:g}); points are in "
        f"the mesh's frame and unit (metres): is the cloud in millimetres, or not aligned with the model?"
    )

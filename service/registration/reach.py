"""How far from its model a cloud may lie and still be registered.

A deformed organ's surface stays within about one size of its rest bounding box, so a cloud far
past that is not the organ: most often one in the wrong unit (millimetres against a model in
metres lies hundreds of sizes off), or an unaligned camera frame. Far enough off, the distance's
gradient is lost to rounding (every closest point ties at 1e16 sizes) and the rest state looked
like an optimum. A session refuses (:func:`check_reach`, a ValueError: a 422) a cloud whose
median point lies past REACH sizes (a unit mistake), and one with any point past FAR sizes (no
depth camera's stray point lies there; 199 of 400 points at 1e20 m leave the median near, and
drown the gradient). Stray points nearer than FAR are a depth camera's outliers, for the robust
losses; the engine never calls an answer converged whose rms distance lies past the reach
(:meth:`Box.within`).
"""

from __future__ import annotations

import math

import numpy as np

Array = np.ndarray

#: how many model sizes (its rest bounding box's diagonal) from that box a cloud's median point
#: may lie, and an answer's rms distance: 10x leaves room for any deformation and catches a
#: millimetre cloud (~500 sizes off)
REACH = 10.0
#: how many model sizes from that box any one point may lie: 200 m for a 20 cm liver, past any
#: depth camera's range, and far below where rounding ties every closest point (1e16 sizes)
FAR = 1000.0


class Box:
    """A model's rest bounding box and its size (the diagonal, m). Shape: nodes (n, 3)."""

    def __init__(self, nodes: Array) -> None:
        self.lo, self.hi = nodes.min(axis=0), nodes.max(axis=0)
        self.size = float(np.linalg.norm(self.hi - self.lo)) or 1.0

    def offsets(self, points: Array) -> Array:
        """Each point's (m, 3) distance from the box (0 inside), (m,)."""
        # per coordinate, how far past the nearer face (zero inside): whole-array, no loop over points
        gap = np.maximum(np.maximum(self.lo - points, points - self.hi), 0.0)
        return np.sqrt(np.einsum("ij,ij->i", gap, gap))

    def median_offset(self, points: Array) -> float:
        """The median over the points (m, 3) of their distance from the box (0 inside)."""
        return float(np.median(self.offsets(points)))

    def within(self, distance: float) -> bool:
        """Whether a (finite) distance from the box is within the reach."""
        return math.isfinite(distance) and distance <= REACH * self.size


def check_reach(box: Box, points: Array) -> None:
    """ValueError, in one line, where the cloud's median point lies farther than REACH model
    sizes from the model's box (naming the likely unit mistake), or any point farther than FAR
    (naming how many and how far)."""
    offsets = box.offsets(points)
    median = float(np.median(offsets))
    if not box.within(median):
        raise ValueError(
            f"points lie too far from the model: the median point is {median:.3g} m from its bounding box, "
            f"{median / box.size:.3g} times its size of {box.size:.3g} m (at most {REACH:g}); points are in "
            f"the mesh's frame and unit (metres): is the cloud in millimetres, or not aligned with the model?"
        )
    bound = FAR * box.size
    far = offsets > bound
    if far.any():
        farthest = float(offsets.max())
        raise ValueError(
            f"points lie too far from the model: {int(far.sum())} of {len(points)} points are more than "
            f"{bound:.3g} m ({FAR:g} times its size of {box.size:.3g} m) from its bounding box, the farthest "
            f"{farthest:.3g} m; no depth camera sees that far: drop them, or is the cloud not in metres?"
        )

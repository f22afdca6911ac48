"""The share of a frame's time budget kept for what follows its solve (the outputs, the error
estimate, the commit), sized by what that took on the session's last frames."""

from __future__ import annotations

import collections
import statistics

#: the frames whose time after the solve sizes the next one's reserve (:class:`Reserve`):
#: their median rides out one slow frame (a collection, a busy core) without chasing it
AFTER_SOLVE_FRAMES = 5
#: the most of a time budget kept for what follows the solve: the solve keeps the rest. Outputs
#: slower than half the budget cannot fit beside a solve that makes progress, so past it the frame
#: overruns by their excess instead (review s24: one 1.3 s frame at a 150 ms budget left the next
#: frames 0 iterations, their forces frozen while the load grew)
RESERVE_SHARE = 0.5


class Reserve:
    """One session's reserve: the seconds each of its last frames took after its solve."""

    def __init__(self) -> None:
        self.after_solve: collections.deque[float] = collections.deque(maxlen=AFTER_SOLVE_FRAMES)

    def __call__(self, budget: float) -> float:
        """Seconds of a frame's time `budget` kept for what follows its solve: the median of what
        that took on the session's last AFTER_SOLVE_FRAMES frames, its first frame left out (it
        pays one-time costs, the first use of kernels and caches), 0 before there are any; so
        that the whole frame, not only its optimiser, fits in the budget where it can. The lower
        median, so that one slow frame among the first few is ridden out as among five (of two,
        the faster), and never past RESERVE_SHARE of the budget: a reserve past it left the
        solve no time, frame after frame."""
        if not self.after_solve:
            return 0.0
        return min(statistics.median_low(self.after_solve), RESERVE_SHARE * budget)

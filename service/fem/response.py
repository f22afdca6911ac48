"""A support's response through a factorisation: K^-1 on each unit force of the support, read
at some nodes, in blocks of right-hand sides, its last columns on a spare core.

The FEM's Jacobians in full are this response (FEMOperator in fem/model.py: at rest once, at an
equilibrium for each Levenberg-Marquardt step).
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable

import numpy as np

from ..forward import ForwardFailed
from ..spare import Beside

Array = np.ndarray
Solve = Callable[[Array], Array]

#: A factorisation's cost in back-substitutions (in blocks): the paper's liver, 27 ms against
#: 0.9 ms, one thread. The Jacobian's columns split so that the spare core's share plus its own
#: factorisation take as long as the caller's; under twice this, no split pays
FACTOR_IN_SOLVES = 30


def support_response(
    solve: Solve,
    cols: Array,
    read: Array,
    n_free: int,
    deadline: float | None = None,
    block: int = 256,
    beside: Callable[[], Solve] | None = None,
) -> Array:
    """K^-1 applied to each unit force on the support (its rows `cols` of the free system, 3k),
    read at the nodes' rows `read` (3p, -1 on fixed dofs: they never move), in blocks of `block`
    right-hand sides (a block's solution is 3n x block; the whole would be 3n x 3k);
    past `deadline`, ForwardFailed between blocks. `beside`: given, the last columns go to a
    spare core (``spare.Beside``), which calls it for a solve of its own, a second factor of
    `solve`'s matrix; the caller solves them itself if no thread began. Shape: (3p, 3k)."""
    n_cols = cols.size
    J = np.zeros((read.size, n_cols))

    def fill(solve: Solve, start: int, stop: int) -> None:
        for lo in range(start, stop, block):
            if lo and deadline is not None and time.perf_counter() > deadline:
                raise ForwardFailed(
                    "time_limit", f"time budget spent forming the Jacobian, after {lo} of {n_cols} solves"
                )
            hi = min(lo + block, stop)
            rhs = np.zeros((n_free, hi - lo))
            rhs[cols[lo:hi], np.arange(hi - lo)] = 1.0
            X = solve(rhs)
            J[read >= 0, lo:hi] = X[read[read >= 0]]

    mine = n_cols if beside is None else min(n_cols, (n_cols + FACTOR_IN_SOLVES) // 2)  # both halves end together
    other = None
    if beside is not None and mine < n_cols - FACTOR_IN_SOLVES // 2:

        def theirs() -> bool:
            fill(beside(), mine, n_cols)
            return True

        other = Beside(theirs)
    try:
        fill(solve, 0, mine)
    except BaseException:
        if other is not None:  # its solver must be free before the next Jacobian factors on it
            with contextlib.suppress(Exception):
                other.taken()
        raise
    if other is not None and other.taken() is None:  # no thread began it: no second factor
        fill(solve, mine, n_cols)
    return J

"""A spare core for a frame's independent work: run a job beside the caller, or inline.

On a machine with a core to spare, parts of a warm network frame overlap: its rest state with
its start, the distance's Gram with the Jacobian, the estimate's rotations with its internal
force, and the outputs at each Levenberg-Marquardt trial point with that point's distance
(docs/performance.md). A job goes to a shared pool of one thread per core beyond the first;
where no thread has started it by the time its result is needed (every core busy with other
sessions' frames), the caller cancels it and runs it itself, so a loaded server pays a submit
(tens of microseconds), never a wait in a queue.
"""

from __future__ import annotations

import concurrent.futures
import os
import threading
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")

_pool: concurrent.futures.ThreadPoolExecutor | None = None
_lock = threading.Lock()


def threads() -> int:
    """The spare threads: the cores beside the caller's (one at least), so that a frame never
    runs more threads than there are cores."""
    return max((os.cpu_count() or 1) - 1, 1)


def _executor() -> concurrent.futures.ThreadPoolExecutor:
    global _pool
    if _pool is None:
        with _lock:
            if _pool is None:
                _pool = concurrent.futures.ThreadPoolExecutor(threads(), thread_name_prefix="elastreg-spare")
    return _pool


class Beside(Generic[T]):
    """`fn()` started on a spare thread; :meth:`result` waits for it, or runs it inline if no
    thread had begun it. The job must touch nothing the caller changes meanwhile."""

    def __init__(self, fn: Callable[[], T]) -> None:
        self._fn = fn
        self._future = _executor().submit(fn)

    def result(self) -> T:
        if self._future.cancel():  # still queued: every spare thread is busy
            return self._fn()
        return self._future.result()

    def drop(self) -> None:
        """No longer wanted: cancelled if no thread has begun it, else left to finish."""
        self._future.cancel()

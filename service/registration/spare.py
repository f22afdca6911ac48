"""A spare core for a frame's independent work: run a job beside the caller, or inline.

A warm frame's rest-state evaluation does not depend on its start's, and on a machine with a
core to spare the two can overlap (docs/performance.md). A job goes to a shared pool of one
thread per core; where no thread has started it by the time its result is needed (every core
busy with other sessions' frames), the caller cancels it and runs it itself, so a loaded server
pays a submit (tens of microseconds), never a wait in a queue.
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


def _executor() -> concurrent.futures.ThreadPoolExecutor:
    global _pool
    if _pool is None:
        with _lock:
            if _pool is None:
                _pool = concurrent.futures.ThreadPoolExecutor(os.cpu_count() or 1, thread_name_prefix="elastreg-spare")
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

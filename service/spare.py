"""A spare core for a frame's independent work: run a job beside the caller, or inline.

On a machine with a core to spare, parts of a warm network frame overlap: its rest state with
its start, the distance's Gram with the Jacobian, the estimate's rotations with its internal
force, the outputs at each Levenberg-Marquardt trial point with that point's distance, the field
with the declared noise's term; the Newton method's Jacobian solves half its columns there, on a
factor of its own, and its factorisations and assemblies take that core too (:func:`helping`;
docs/performance.md). A job goes to a shared pool of one thread per core
beyond the first; where no thread has started it by the time its result is needed (every core
busy with other sessions' frames), the caller cancels it and runs it itself. A core is spare
only while fewer frames are in progress in this process than there are cores (:func:`frame`): on
a loaded server every job runs inline, since a third thread on two busy cores cost 6-17 % of the
throughput of 4 and 16 streams (docs/performance.md).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import os
import threading
from collections.abc import Callable, Iterator
from typing import Generic, TypeVar

T = TypeVar("T")

_pool: concurrent.futures.ThreadPoolExecutor | None = None
_lock = threading.Lock()
_frames = 0  # frames in progress in this process
_outstanding = 0  # jobs handed to the pool and neither ended nor cancelled
_running = threading.local()  # .frame: whether this thread runs a frame now


@contextlib.contextmanager
def frame() -> Iterator[None]:
    """Counts a frame in progress while the block runs (a session's frame), and marks the
    calling thread as a frame's own (:func:`helping`)."""
    global _frames
    with _lock:
        _frames += 1
    outer = getattr(_running, "frame", False)
    _running.frame = True
    try:
        yield
    finally:
        _running.frame = outer
        with _lock:
            _frames -= 1


def spare() -> bool:
    """Whether a core is spare: fewer frames in progress than cores."""
    return _frames < (os.cpu_count() or 1)


def helping() -> bool:
    """Whether the calling thread runs a frame, a core is spare and the pool has no job: the
    FEM's own work may then take that core (a factorisation's second thread, an assembly's
    other half). A trainer's worker processes run no frames, so they never take one: they fill
    the cores themselves. A job in the pool (method auto's network field beside its Newton
    correction) keeps the factorisation on one thread, not two on a busy core."""
    return getattr(_running, "frame", False) and spare() and _outstanding == 0


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
    """`fn()` started on a spare thread where a core is spare; :meth:`result` waits for it, or
    runs it inline if no thread had begun it (or none was asked to). The job must touch nothing
    the caller changes meanwhile."""

    def __init__(self, fn: Callable[[], T], start: bool | None = None) -> None:
        """`start`: whether to hand it to a spare thread (default: where a core is spare)."""
        self._fn = fn
        self._future = _submit(fn) if (spare() if start is None else start) else None

    def _not_begun(self) -> bool:
        """Whether it had no thread (none asked, or cancelled now since none had begun it)."""
        if self._future is None:
            return True
        if self._future.cancel():
            self._future = None
            _settle()
            return True
        return False

    def result(self) -> T:
        if self._not_begun():  # no spare thread was free
            return self._fn()
        assert self._future is not None
        return self._future.result()

    def taken(self) -> T | None:
        """Its result if a thread has begun it (waiting for the end), else None: cancelled, for
        a caller that would do the work another way than `fn` (without a second factor, say)."""
        if self._not_begun():
            return None
        assert self._future is not None
        return self._future.result()

    def drop(self) -> None:
        """No longer wanted: cancelled if no thread has begun it, else left to finish."""
        self._not_begun()


def _submit(fn: Callable[[], T]) -> concurrent.futures.Future:
    """`fn` handed to the pool, counted until it ends or is cancelled (:func:`helping`)."""
    global _outstanding

    def counted() -> T:
        try:
            return fn()
        finally:
            _settle()  # before the caller can see the result: its next helping() counts it done

    with _lock:
        _outstanding += 1
    return _executor().submit(counted)


def _settle() -> None:
    global _outstanding
    with _lock:
        _outstanding -= 1

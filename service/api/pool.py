"""The solve pool: a fixed number of threads, and admission control in front of them.

Every engine call runs here, off the event loop. A job is admitted only while the jobs in flight
(running or waiting for a thread) are fewer than ``threads + queue``: past that the caller gets
:class:`Overloaded` at once (HTTP 503 with ``Retry-After``, or a stream's 503 error for that
frame with ``retry_after``) instead of joining a queue without bound. While the server drains
for shutdown every job is refused the same way: retrying reaches the restarted server, or
another replica. A job whose client or session went away before a thread took it is dropped, not
computed (:class:`Dropped`). The count of jobs in flight is kept by the jobs themselves
(released when the thread is done with one, not when its caller stops waiting), so a solve whose
client has gone still counts until it ends: nothing holds a thread that admission does not see.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import threading
from collections.abc import Callable
from typing import Any


class Overloaded(RuntimeError):
    """No room for another job now (HTTP 503; retry after ``retry_after`` seconds)."""

    def __init__(self, message: str, retry_after: int) -> None:
        super().__init__(message)
        self.retry_after = retry_after


class Dropped(RuntimeError):
    """A job not computed: its session closed or its client left before a thread took it."""


class SolvePool:
    """A fixed thread pool for solves; ``await pool.run(fn, ...)`` from the event loop.

    ``queue`` is how many jobs may wait for a thread (None: no bound)."""

    def __init__(self, threads: int, queue: int | None = None, *, retry_after: int = 1) -> None:
        self.threads = threads
        self.queue = queue
        self.retry_after = retry_after
        self.in_flight = 0  # admitted and not finished (running or waiting)
        self.running = 0
        self.refused = 0
        self.dropped = 0
        self.draining = False
        self._lock = threading.Lock()
        self._pool = concurrent.futures.ThreadPoolExecutor(max_workers=threads, thread_name_prefix="elastreg-solve")

    @property
    def capacity(self) -> int | None:
        return None if self.queue is None else self.threads + self.queue

    @property
    def saturated(self) -> bool:
        """Every thread busy and the queue full: the next job would be refused."""
        return self.capacity is not None and self.in_flight >= self.capacity

    def counts(self) -> dict[str, int | None]:
        with self._lock:
            return {
                "in_flight": self.in_flight,
                "running": self.running,
                "capacity": self.capacity,
                "refused": self.refused,
                "dropped": self.dropped,
            }

    async def run(
        self,
        fn: Callable,
        *args,
        cancelled: Callable[[], bool] | None = None,
        done: Callable[[], None] | None = None,
        **kwargs,
    ) -> Any:
        """``fn(*args, **kwargs)`` on a pool thread. ``cancelled()`` is asked when a thread takes
        the job (True: :class:`Dropped`, not run); ``done()`` is called once the job is over:
        refused, run, dropped or failed (from the thread that ended it)."""
        with self._lock:
            refusal = None
            if self.draining:
                refusal = f"the server is shutting down; retry in {self.retry_after} s"
            elif self.capacity is not None and self.in_flight >= self.capacity:
                refusal = (
                    f"the server is at capacity ({self.threads} solves running, {self.queue} "
                    f"waiting); retry in {self.retry_after} s"
                )
            if refusal is None:
                self.in_flight += 1
            else:
                self.refused += 1
        if refusal is not None:
            if done is not None:
                done()
            raise Overloaded(refusal, self.retry_after)

        def job():
            if cancelled is not None and cancelled():
                with self._lock:
                    self.dropped += 1
                raise Dropped("dropped before it ran: its session closed or its client left")
            with self._lock:
                self.running += 1
            try:
                return fn(*args, **kwargs)
            finally:
                with self._lock:
                    self.running -= 1

        def release(_future) -> None:
            with self._lock:
                self.in_flight -= 1
            if done is not None:
                done()

        try:
            future = self._pool.submit(job)
        except RuntimeError:  # the executor has shut down
            release(None)
            raise Overloaded(f"the server is shutting down; retry in {self.retry_after} s", self.retry_after) from None
        future.add_done_callback(release)
        return await asyncio.wrap_future(future)

    async def drain(self, timeout: float) -> bool:
        """Refuse new jobs; wait up to ``timeout`` s for those in flight. True when none is left."""
        self.draining = True
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while self.in_flight and loop.time() < deadline:
            await asyncio.sleep(0.02)
        return self.in_flight == 0

    def shutdown(self) -> None:
        self.draining = True
        self._pool.shutdown(wait=False, cancel_futures=True)

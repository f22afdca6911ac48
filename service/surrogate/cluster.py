"""The Dask plumbing of a data generation (surrogate/data.py): reaching a scheduler, starting local
workers under a held Ctrl-C, waiting for workers, and Dask's errors as one-line ClusterErrors
that say how many paths the data folder keeps for a rerun.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
import signal
import threading
import time
from collections.abc import Iterator
from concurrent.futures import CancelledError  # distributed's FutureCancelledError is one
from pathlib import Path

from .pathfiles import done_indices


class ClusterError(RuntimeError):
    """The Dask scheduler or workers of a generation could not be reached (or went away)."""


@contextlib.contextmanager
def _from_dask(scheduler: str | None, data_dir: Path | None = None) -> Iterator[None]:
    """An OSError (a comm closed, a connect timed out) out of Dask as a ClusterError that says
    which cluster: the writes to the data folder are outside these blocks and keep their own.
    With `data_dir` (paths are being solved) a cluster lost mid-build is one too: its paths
    cancelled (workers killed: the scattered mesh went with them; the scheduler gone) or its
    workers killed too often; the error says how many paths the folder keeps for a rerun."""
    lost: tuple[type[BaseException], ...] = (OSError,)
    if data_dir is not None:
        from distributed.scheduler import KilledWorker

        lost = (OSError, CancelledError, KilledWorker)
    try:
        yield
    except lost as exc:
        where = f"the Dask scheduler at {scheduler}" if scheduler else "the local Dask workers"
        reason = (str(exc).splitlines() or [type(exc).__name__])[0]  # one line: Dask's may run on
        cancelled = r"^\S+ cancelled for reason: (.*?)\.?$"  # a FutureCancelledError: its task's key is noise
        reason = re.sub(cancelled, r"its paths were cancelled: \1", reason)
        if data_dir is None:
            raise ClusterError(f"cannot reach {where}: {reason}") from exc
        kept = len(done_indices(data_dir))
        where = f"the Dask cluster at {scheduler}" if scheduler else where  # its workers, or the scheduler itself
        raise ClusterError(
            f"lost {where} mid-build ({reason}): {kept} load paths kept in {data_dir}; the same command resumes"
        ) from exc


def _probe_scheduler(address: str, seconds: float) -> None:
    """Raise ClusterError unless a Dask scheduler answers at `address` (the comm's handshake)
    within `seconds`. Client(address) alone can wait forever: a port that accepts and never
    answers (a web server, the scheduler's dashboard) leaves its handshake unread, whatever its
    timeout. Here the wait is cancelled at the bound, and the half-open comm goes with it. A
    server that speaks first (an SSH banner) fails the comm's read in any way (a MemoryError for
    a banner read as a frame length): all of them mean that no scheduler is there."""
    from distributed.comm import connect

    async def probe() -> None:
        comm = await connect(address, timeout=seconds)  # retries a refused port until then
        await comm.close()

    try:
        asyncio.run(asyncio.wait_for(probe(), seconds))
    except Exception as exc:  # a timeout, or a server of another protocol: a banner read as a frame length
        raise ClusterError(f"no Dask scheduler answers at {address} within {round(seconds, 1):g} s") from exc


@contextlib.contextmanager
def _quiet(name: str) -> Iterator[None]:
    """The logger `name` silent while the block runs."""
    logger = logging.getLogger(name)
    level = logger.level
    logger.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        logger.setLevel(level)


def _distributed_loggers() -> list[logging.Logger]:
    """distributed's loggers that hold a level of their own (its config sets some: "distributed",
    "distributed.client"...); the others take theirs from these."""
    found = [logging.getLogger(name) for name in list(logging.root.manager.loggerDict)]
    return [lg for lg in found if lg.name.split(".")[0] == "distributed" and lg.level != logging.NOTSET]


def _silence_distributed() -> None:
    """distributed's loggers silent for good: run in each local worker after a Ctrl-C (its
    cancelled paths each logged "Async instruction ... ended with CancelledError")."""
    for logger in _distributed_loggers():
        logger.setLevel(logging.CRITICAL + 1)


@contextlib.contextmanager
def _interrupted_quietly(client, local: bool) -> Iterator[None]:
    """The shutdown after a Ctrl-C without distributed's log lines beside the one-line
    "interrupted": in this process while the block runs, and in the `local` workers (this
    build's own processes: a scheduler's workers are someone else's) for the rest of their life."""
    loggers = _distributed_loggers()
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.CRITICAL + 1)
    try:
        if local and client is not None:
            with contextlib.suppress(Exception):  # workers already gone: nothing left to say anything
                client.run(_silence_distributed)
        yield
    finally:
        for logger, level in zip(loggers, levels, strict=True):
            logger.setLevel(level)


@contextlib.contextmanager
def _sigint_held_from_children() -> Iterator[None]:
    """Ctrl-C held while the block starts worker processes, and raised once it is done (so the
    caller closes what the block started).

    SIGINT is blocked in this thread, and so in every thread and process the block starts: they
    inherit the mask and keep it, since Ctrl-C at a terminal goes to the whole process group and
    each worker printed its own KeyboardInterrupt tracebacks. One that lands meanwhile on an
    older thread (tqdm's monitor, the BLAS pool) is kept by a handler. SIGINT ignored instead
    (which the workers inherit too) lost a Ctrl-C in the seconds a LocalCluster takes to start.
    """
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        yield
        return
    from multiprocessing import resource_tracker

    # started now, not by the block's first worker: its start unblocks SIGINT in the thread that
    # starts it, and that thread then starts a worker
    resource_tracker.ensure_running()
    caught: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})  # one pending lands on the handler
        signal.signal(signal.SIGINT, previous)
    if caught:
        raise KeyboardInterrupt


def _wait_for_workers(client, address: str, seconds: float, bar) -> None:
    """Raise ClusterError unless the scheduler at `address` has a worker within `seconds`; the
    progress bar says that it waits, and how long. Without this, a scheduler with no workers (not
    started yet, or pointed at another scheduler) held the build in scatter for Dask's own
    timeout with no word, then blamed the connection ("No valid workers found")."""
    if client.nthreads():
        return
    bar.set_postfix_str(f"waiting up to {round(seconds, 1):g} s for a worker at {address}")
    try:
        client.wait_for_workers(1, timeout=seconds)
    except TimeoutError as exc:  # an OSError: raised as it is, _from_dask would call it unreachable
        raise ClusterError(
            f"the Dask scheduler at {address} has no workers (waited {round(seconds, 1):g} s): "
            f"start some with `dask worker {address}`"
        ) from exc
    bar.set_postfix_str("")


#: seconds local Dask workers cost a timed generation: their start until the first path comes
#: back (the process spawns, the imports, the solver's compiled kernels loading; a bare
#: LocalCluster starts in 2 s of it) and their close (cancelled paths: the nanny waits 4 s). Measured
#: 12-16 s + 4 s for 2 workers on the bar on a shared 2-core machine, where this process solves
#: the same paths in 15 ms each after 1.6 s of warm-up
LOCAL_CLUSTER_COST_S = 20.0


def local_workers_pay(seconds: float, workers: int) -> bool:
    """Whether `seconds` of data generation are worth starting `workers` local workers for: they
    beat this process once (seconds - cost) * workers > seconds, past twice the cost for the
    default 2, less for more; one worker never does."""
    return workers > 1 and seconds > LOCAL_CLUSTER_COST_S * workers / (workers - 1)


#: times a generation sends the mesh again to local workers their nannies restarted (killed: the
#: OOM killer on a big mesh) before it gives up with a ClusterError
LOCAL_RESTARTS = 3


#: paths a generation keeps in flight per worker thread (one solving, the next ones queued)
PATHS_PER_THREAD = 3


#: seconds before the data's end that a worker stops its path: what the path's result takes to
#: come back, so that the build hears of a path the clock cut (how long it ran: the refusal's
#: figures) before it stops listening. Without it a LocalCluster's cut path came back after the
#: build had stopped waiting, on a 2-core machine under a load of 9
WORKER_STOP_EARLY_S = 1.0


#: seconds between looks at a scheduler's worker threads (a cluster's workers may join late)
SLOTS_CHECK_S = 5.0


def _slots(client) -> int:
    """Paths to keep in flight on the client's cluster: PATHS_PER_THREAD per worker thread."""
    return PATHS_PER_THREAD * max(sum(client.nthreads().values()), 1)


def _connect_seconds(deadline: float | None) -> float:
    """Dask's connect timeout (distributed.comm.timeouts.connect), cut to what is left before
    `deadline` (a time.perf_counter() value)."""
    import dask.config
    from dask.utils import parse_timedelta

    seconds = float(parse_timedelta(dask.config.get("distributed.comm.timeouts.connect"), default="seconds"))
    if deadline is not None:
        seconds = max(min(seconds, deadline - time.perf_counter()), 0.1)
    return seconds

"""Training data: random local surface loads, solved by the FEM along load paths.

One *path* is one random load grown in `steps` equal increments from rest; each converged step
is a sample, so a path costs little more than one solve (every step warm-starts from the last).
A path is a pure function of (scene, seed, index): the work maps over indices with Dask, each
finished path is written to its own file at once (atomically), and a rerun skips the indices
already on disk, so an interrupted run resumes where it stopped and loses nothing.

Shapes on disk, per path file ``path_NNNNNN.npz``: ``forces`` (s, r, 3) float32 on the region
nodes, ``u`` (s, n, 3) float32 for all nodes, ``newton_iterations`` (s,), s <= steps.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import itertools
import logging
import os
import re
import signal
import tempfile
import threading
import time
from collections.abc import Generator, Iterator
from concurrent.futures import CancelledError  # distributed's FutureCancelledError is one
from functools import lru_cache
from pathlib import Path

import numpy as np

from ..fem.assembly import Assembler
from ..fem.material import NeoHookean
from ..fem.newton import NewtonOptions, NewtonSolver
from ..mesh import TetMesh
from ..optional import need

log = logging.getLogger(__name__)

Array = np.ndarray


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


@dataclasses.dataclass(frozen=True)
class LoadSpec:
    """The load distribution a scene declares (SCENES.md [training])."""

    region: tuple[int, ...]  # free surface node ids where loads may act
    max_force: float  # N, largest total load of one sample
    patch_nodes: tuple[int, int] = (5, 40)
    steps: int = 5  # samples per path
    multi_patch: float = 0.2  # fraction of paths with two patches
    normal_fraction: float = 0.5  # mean share of the outward normal in a load's direction
    pull_fraction: float = 2.0 / 3.0  # outward pulls (a grasper retracting) vs pushes
    twist_fraction: float = 0.0  # patches loaded by a torque (tangential, turning about the centre)
    seed: int = 0


def _unit(v: Array) -> Array:
    return v / np.linalg.norm(v)


def sample_path_load(mesh: TetMesh, spec: LoadSpec, rng: np.random.Generator) -> Array:
    """The final (largest) load of one path, on the region nodes. Shape: (r, 3).

    A patch is the k region nodes nearest (along the surface) to a random region node, with k
    uniform in patch_nodes. Its direction mixes the outward normal and a random tangent: the
    normal share a ~ Beta(2 nf, 2 (1 - nf)) has mean nf = `normal_fraction`, and the normal
    part points outwards (a pull) with probability `pull_fraction`. The total force spreads evenly or as a
    smooth bump over the patch. With probability `twist_fraction` a patch instead carries a torque:
    each node pulls tangentially about the patch's centre (a twisting grip; the total is then the
    sum of the nodal magnitudes). The path's total magnitude is max_force * sqrt(U(0.05, 1)), so
    that with the path's equal steps the samples cover magnitudes roughly uniformly.
    """
    region = np.asarray(spec.region)
    in_region = np.zeros(mesh.n_nodes, bool)
    in_region[region] = True
    pos = np.full(mesh.n_nodes, -1)
    pos[region] = np.arange(region.size)
    g = np.zeros((region.size, 3))
    n_patches = 2 if rng.random() < spec.multi_patch else 1
    total = spec.max_force * np.sqrt(rng.uniform(0.05, 1.0))
    shares = rng.dirichlet(np.ones(n_patches)) if n_patches > 1 else np.ones(1)
    lo, hi = spec.patch_nodes
    for share in shares:
        centre = int(rng.choice(region))
        k = int(rng.integers(lo, hi + 1))
        patch = _region_patch(mesh, centre, k, in_region)
        normal = mesh.patch_normal(patch)
        tangent = _unit(np.cross(normal, _unit(rng.normal(size=3))))
        nf = min(max(spec.normal_fraction, 1e-3), 1 - 1e-3)
        a = rng.beta(2.0 * nf, 2.0 * (1.0 - nf))
        sign = 1.0 if rng.random() < spec.pull_fraction else -1.0
        direction = _unit(sign * a * normal + np.sqrt(1.0 - a * a) * tangent)
        if rng.random() < 0.5:
            w = np.ones(patch.size)
        else:
            d = np.linalg.norm(mesh.nodes[patch] - mesh.nodes[centre], axis=1)
            w = 1.0 - (d / (d.max() * 1.05 + 1e-300)) ** 2
        if spec.twist_fraction > 0 and rng.random() < spec.twist_fraction:
            arm = mesh.nodes[patch] - mesh.nodes[patch].mean(axis=0)
            turn = np.cross(normal, arm) * rng.choice([-1.0, 1.0])
            turn /= np.maximum(np.linalg.norm(turn, axis=1, keepdims=True), 1e-300)
            g[pos[patch]] += turn * (w / w.sum() * total * share)[:, None]
            continue
        g[pos[patch]] += np.outer(w / w.sum(), direction) * (total * share)
    return g


def _region_patch(mesh: TetMesh, centre: int, k: int, in_region: Array) -> Array:
    """The k region nodes nearest to `centre` along the surface."""
    from scipy.sparse import csgraph

    dist = csgraph.dijkstra(mesh.surface_graph, indices=centre)
    cand = np.flatnonzero(in_region & np.isfinite(dist))
    return cand[np.argsort(dist[cand], kind="stable")[:k]]


@lru_cache(maxsize=2)
def _solver(mesh: TetMesh, material: NeoHookean, rtol: float, max_newton: int | None) -> NewtonSolver:
    """One Newton solver per worker process and problem (it owns a factorisation)."""
    options = NewtonOptions(rtol=rtol) if max_newton is None else NewtonOptions(rtol=rtol, max_iter=max_newton)
    return NewtonSolver(Assembler(mesh, material), options)


def solve_path(
    mesh: TetMesh, material: NeoHookean, spec: LoadSpec, index: int, rtol: float = 1e-7, max_newton: int | None = None
) -> dict:
    """Solve path `index` step by step; keeps the steps that converged (a pure function).

    `max_newton`: Newton iterations one step may take before the path stops there (default
    NewtonOptions.max_iter).
    """
    rng = np.random.default_rng([spec.seed, index])
    g_region = sample_path_load(mesh, spec, rng)
    solver = _solver(mesh, material, rtol, max_newton)
    region = np.asarray(spec.region)
    forces, us, its = [], [], []
    u = None
    t0 = time.perf_counter()
    for step in range(1, spec.steps + 1):
        g = np.zeros((mesh.n_nodes, 3))
        g[region] = g_region * (step / spec.steps)
        res = solver.solve(g, u)
        if not res.converged:
            log.info("path %d: step %d did not converge (%s)", index, step, res.status)
            break
        u = res.u
        forces.append(g[region])
        us.append(u)
        its.append(res.iterations)
    return {
        "index": index,
        "forces": np.asarray(forces, np.float32).reshape(-1, region.size, 3),
        "u": np.asarray(us, np.float32).reshape(-1, mesh.n_nodes, 3),
        "newton_iterations": np.asarray(its, np.int32),
        "seconds": time.perf_counter() - t0,
    }


# -- the data set on disk -------------------------------------------------------------------


_PATH_NAME = re.compile(r"path_(\d{6})\.npz")


def path_file(data_dir: Path, index: int) -> Path:
    return Path(data_dir) / f"path_{index:06d}.npz"


def done_indices(data_dir: Path) -> set[int]:
    """Indices of finished paths (half-written files are hidden temporaries, never matched)."""
    names = (p.name for p in Path(data_dir).glob("path_*.npz"))
    return {int(m.group(1)) for m in map(_PATH_NAME.fullmatch, names) if m}


def write_path(data_dir: Path, result: dict) -> None:
    """Atomic write: a half-written file never looks like a finished path."""
    final = path_file(data_dir, result["index"])
    fd, name = tempfile.mkstemp(prefix=f".{final.stem}-", suffix=".tmp.npz", dir=final.parent)
    tmp = Path(name)  # a name of its own: two builds of one scene may write the same path
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, forces=result["forces"], u=result["u"], newton_iterations=result["newton_iterations"])
        os.replace(tmp, final)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError) and exc.filename is None:  # written through the fd: it names no file
            raise OSError(exc.errno, exc.strerror, str(final)) from exc
        raise


def load_dataset(data_dir: Path, indices: list[int] | None = None) -> tuple[Array, Array, Array]:
    """All samples on disk: forces (N, r, 3), u (N, n, 3) float32, and each sample's path index."""
    idx = sorted(done_indices(data_dir)) if indices is None else sorted(indices)
    F, U, P = [], [], []
    for i in idx:
        with np.load(path_file(data_dir, i)) as z:
            F.append(z["forces"])
            U.append(z["u"])
            P.append(np.full(len(z["forces"]), i))
    if not F:
        raise FileNotFoundError(f"no samples in {data_dir}")
    return np.concatenate(F), np.concatenate(U), np.concatenate(P)


def generate(
    mesh: TetMesh,
    material: NeoHookean,
    spec: LoadSpec,
    data_dir: Path,
    n_paths: int,
    *,
    workers: int = 2,
    scheduler: str | None = None,
    progress: bool = True,
    max_newton: int | None = None,
    until: float | None = None,
    deadline: float | None = None,
) -> Generator[dict, None, None]:
    """Solve paths 0..n_paths-1 that are not on disk yet, in parallel; yields each as written.

    With `scheduler` the work goes to that Dask cluster; otherwise a LocalCluster of `workers`
    single-threaded processes (one per core: the factorisation is the hot spot and threads
    would only fight over it). With workers=0 it runs in this process (tests, debugging).
    `max_newton` caps each step's Newton iterations (solve_path); a data folder should hold
    paths of one cap (build.data_key). `until` (a time.perf_counter() value): the generation
    stops there, with workers even while paths are being solved (those still running are
    dropped), in this process before a path that the slowest so far says would end past it
    (path_fits); local workers start only where the time to
    it pays for them (local_workers_pay), else the paths are solved in this process.
    Connecting to `scheduler`, and waiting for its first worker, each take at most Dask's connect
    timeout (distributed.comm.timeouts.connect), never past `deadline` (a time.perf_counter() value:
    the build's end); the wait for a worker never past `until` either. Local workers that their
    nannies restart mid-build (killed: the OOM killer on a big mesh) are sent the mesh again and
    the paths in flight solved again, up to LOCAL_RESTARTS times; a cluster lost otherwise is a
    ClusterError that says how many paths the folder keeps.
    """
    data_dir = Path(data_dir)
    data_dir.mkdir(parents=True, exist_ok=True)
    on_disk = frozenset(i for i in done_indices(data_dir) if i < n_paths)  # listed once, not once per path
    # lazy: a timed build's samples are a ceiling (millions of paths), its clock what ends it
    todo = (i for i in range(n_paths) if i not in on_disk)
    bar = _progress(n_paths, len(on_disk), progress)
    if len(on_disk) == n_paths:
        bar.close()
        return
    if (
        scheduler is None
        and workers
        and until is not None
        and not local_workers_pay(until - time.perf_counter(), workers)
    ):
        log.info("%.1f s of data is too short for local workers to pay off: solved here", until - time.perf_counter())
        workers = 0
    if workers == 0 and scheduler is None:
        took: list[float] = []  # the solve seconds of this run's paths: what the next may take
        for i in todo:
            if not path_fits(until, took):  # a path is not cut: none starts that would end past it
                break
            result = solve_path(mesh, material, spec, i, max_newton=max_newton)
            took.append(result["seconds"])
            write_path(data_dir, result)
            bar.update(1)
            bar.set_postfix(samples=_count(bar, result))
            yield result
        bar.close()
        return

    distributed = need("dask.distributed", "training with worker processes")
    Client, LocalCluster, as_completed = distributed.Client, distributed.LocalCluster, distributed.as_completed

    cluster = client = None
    try:
        if scheduler is None:
            one_thread = {k: "1" for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")}
            with _from_dask(None), _sigint_held_from_children():
                bar.set_postfix_str(f"starting {workers} local Dask workers")  # a Ctrl-C from here on is held
                cluster = LocalCluster(
                    n_workers=workers,
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address=":0",
                    env=one_thread,
                )
            bar.set_postfix_str("")
        else:
            _probe_scheduler(scheduler, _connect_seconds(deadline))
        with _from_dask(scheduler):
            client = Client(scheduler or cluster)
            if scheduler is not None:
                _wait_for_workers(client, scheduler, _connect_seconds(until if until is not None else deadline), bar)
            sent = client.scatter([mesh, material, spec], broadcast=True)
            pending: Iterator[int] = iter(todo)
            in_flight: dict = {}  # future -> its path's index, until written

            def submit(n: int) -> list:
                """The next n paths, in index order."""
                indices = list(itertools.islice(pending, n))
                futures = [client.submit(solve_path, *sent, i, max_newton=max_newton, pure=False) for i in indices]
                in_flight.update(zip(futures, indices, strict=True))
                return futures

            def start(n: int):
                """Paths as they finish, the next n first, within the clock."""
                timeout = None if until is None else max(until - time.perf_counter(), 1e-3)
                return as_completed(submit(n), timeout=timeout)

            # a few paths per worker thread in flight, topped up as they finish: submitting every
            # path at once spent a timed build's minutes in Dask's bookkeeping (100,000 paths)
            slots, checked = _slots(client), time.perf_counter()
            done, restarts = start(slots), 0
        while True:
            try:
                fut = next(done)
            except (StopIteration, TimeoutError):  # all written, or the clock ran out
                return
            with _from_dask(scheduler, data_dir):
                try:
                    result = fut.result()
                except CancelledError:
                    if scheduler is not None or restarts == LOCAL_RESTARTS:
                        raise
                    # local workers killed (the OOM killer) and restarted by their nannies: the
                    # mesh scattered to them went too, and every path in flight with it
                    restarts += 1
                    lost = sorted(in_flight.values())
                    client.cancel(list(in_flight))
                    in_flight.clear()
                    log.warning("the local Dask workers restarted: the mesh sent again, %d paths again", len(lost))
                    client.wait_for_workers(workers, timeout=_connect_seconds(deadline))
                    sent = client.scatter([mesh, material, spec], broadcast=True)
                    pending = itertools.chain(lost, pending)
                    done = start(slots)
                    continue
                more = 1
                if scheduler is not None and time.perf_counter() - checked > SLOTS_CHECK_S:  # workers may join
                    slots, wanted, checked = _slots(client), slots, time.perf_counter()
                    more += max(slots - wanted, 0)
                done.update(submit(more))
            in_flight.pop(fut, None)
            write_path(data_dir, result)
            bar.update(1)
            bar.set_postfix(samples=_count(bar, result))
            fut.release()
            yield result
    finally:
        bar.close()
        if client is not None:
            with _quiet("distributed.client"):  # a lost scheduler: its reconnect, cancelled, logs a traceback
                client.close()
        if cluster is not None:
            cluster.close()


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


def path_fits(until: float | None, took: list[float], now: float | None = None) -> bool:
    """Whether a path begun `now` (default: the clock) ends by `until` (time.perf_counter()
    values; None: no clock), judged by the slowest of the paths solved so far (`took`, their
    solve seconds: a path's loads set its Newton work, and the slowest is the cautious figure;
    the solver's one-time set-up is not in them). With none solved, any path begun before it:
    a path started just before the clock once ran 5 s past it on a 3,003-node liver."""
    if until is None:
        return True
    now = time.perf_counter() if now is None else now
    return now + max(took, default=0.0) <= until


#: times a generation sends the mesh again to local workers their nannies restarted (killed: the
#: OOM killer on a big mesh) before it gives up with a ClusterError
LOCAL_RESTARTS = 3
#: paths a generation keeps in flight per worker thread (one solving, the next ones queued)
PATHS_PER_THREAD = 3
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


def _progress(total: int, initial: int, enabled: bool):
    bar = need("tqdm.auto", "the trainer's progress bar").tqdm(
        total=total, initial=initial, desc="load paths", unit="path", disable=not enabled
    )
    bar.samples = 0
    return bar


def _count(bar, result: dict) -> int:
    bar.samples += len(result["forces"])
    return bar.samples

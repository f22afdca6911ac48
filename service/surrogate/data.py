"""Training data: random local surface loads, solved by the FEM along load paths.

One *path* is one random load grown in `steps` equal increments from rest; each converged step
is a sample, so a path costs little more than one solve (every step warm-starts from the last).
A path is a pure function of (scene, seed, index): the work maps over indices with Dask, each
finished path is written to its own file at once (atomically), and a rerun skips the indices
already on disk, so an interrupted run resumes where it stopped and loses nothing.

The files on disk are pathfiles.py's, the Dask plumbing cluster.py's.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import logging
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
from .cluster import (
    LOCAL_RESTARTS,
    SLOTS_CHECK_S,
    WORKER_STOP_EARLY_S,
    _connect_seconds,
    _from_dask,
    _interrupted_quietly,
    _probe_scheduler,
    _quiet,
    _sigint_held_from_children,
    _slots,
    _wait_for_workers,
    local_workers_pay,
)
from .pathfiles import done_indices, intact_indices, load_dataset, path_file, write_path, writing

# the data set's files are read through this module too (pathfiles.py holds them)
__all__ = [
    "LoadSpec",
    "done_indices",
    "generate",
    "load_dataset",
    "path_file",
    "path_fits",
    "sample_path_load",
    "solve_path",
    "write_path",
]

log = logging.getLogger(__name__)

Array = np.ndarray


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
    keep_off: tuple[int, ...] = ()  # region nodes no load touches (sites held out of the build)


def _unit(v: Array) -> Array:
    return v / np.linalg.norm(v)


def sample_path_load(mesh: TetMesh, spec: LoadSpec, rng: np.random.Generator) -> Array:
    """The final (largest) load of one path, on the region nodes. Shape: (r, 3).

    A patch is the k region nodes nearest (along the surface) to a random region node, with k
    uniform in patch_nodes. With `keep_off`, both avoid the kept-off nodes and the surface is
    walked around them, not across (load_surface): a patch stays on one side of a held-out area.
    Its direction mixes the outward normal and a random tangent: the
    normal share a ~ Beta(2 nf, 2 (1 - nf)) has mean nf = `normal_fraction`, and the normal
    part points outwards (a pull) with probability `pull_fraction`. The total force spreads evenly or as a
    smooth bump over the patch. With probability `twist_fraction` a patch instead carries a torque:
    each node pulls tangentially about the patch's centre (a twisting grip; the total is then the
    sum of the nodal magnitudes). The path's total magnitude is max_force * sqrt(U(0.05, 1)), so
    that with the path's equal steps the samples cover magnitudes roughly uniformly.
    """
    region = np.asarray(spec.region)
    graph, in_region, centres = load_surface(mesh, spec)
    pos = np.full(mesh.n_nodes, -1)
    pos[region] = np.arange(region.size)
    g = np.zeros((region.size, 3))
    n_patches = 2 if rng.random() < spec.multi_patch else 1
    total = spec.max_force * np.sqrt(rng.uniform(0.05, 1.0))
    shares = rng.dirichlet(np.ones(n_patches)) if n_patches > 1 else np.ones(1)
    lo, hi = spec.patch_nodes
    for share in shares:
        centre = int(rng.choice(centres))
        k = int(rng.integers(lo, hi + 1))
        patch = _region_patch(graph, centre, k, in_region)
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


@lru_cache(maxsize=4)
def load_surface(mesh: TetMesh, spec: LoadSpec) -> tuple:
    """Where `spec`'s loads go: the surface graph they are spread along, the mask of nodes they
    may take, and the patch centres (mesh ids). Without keep_off: the whole surface graph, the
    region, every region node (the draws of a spec from before the field). With it: the graph
    without the kept-off nodes' edges, the region less them, and the nodes of its pieces that
    hold the smallest patch (a piece cut off between held-out areas may hold fewer)."""
    region = np.asarray(spec.region)
    allowed = np.zeros(mesh.n_nodes, bool)
    allowed[region] = True
    if not spec.keep_off:
        return mesh.surface_graph, allowed, region
    allowed[list(spec.keep_off)] = False
    nodes = np.flatnonzero(allowed)
    graph, pieces = mesh.surface_pieces(nodes)
    sizes = np.bincount(pieces)
    return graph, allowed, nodes[sizes[pieces] >= spec.patch_nodes[0]]


def _region_patch(graph, centre: int, k: int, in_region: Array) -> Array:
    """The k region nodes nearest to `centre` along the surface (`graph`'s edges)."""
    from scipy.sparse import csgraph

    dist = csgraph.dijkstra(graph, indices=centre)
    cand = np.flatnonzero(in_region & np.isfinite(dist))
    return cand[np.argsort(dist[cand], kind="stable")[:k]]


@lru_cache(maxsize=2)
def _solver(mesh: TetMesh, material: NeoHookean, rtol: float, max_newton: int | None) -> NewtonSolver:
    """One Newton solver per worker process and problem (it owns a factorisation)."""
    options = NewtonOptions(rtol=rtol) if max_newton is None else NewtonOptions(rtol=rtol, max_iter=max_newton)
    return NewtonSolver(Assembler(mesh, material), options)


def solve_path(
    mesh: TetMesh,
    material: NeoHookean,
    spec: LoadSpec,
    index: int,
    rtol: float = 1e-7,
    max_newton: int | None = None,
    stop_at: float | None = None,
) -> dict:
    """Solve path `index` step by step; keeps the steps that converged (a pure function).

    `max_newton`: Newton iterations one step may take before the path stops there (default
    NewtonOptions.max_iter). `stop_at` (a time.time() value: a wall clock, which a Dask worker
    shares with the build, on another machine as far as their clocks agree): no Newton iteration
    begins that would end past it (NewtonSolver.solve's deadline), and a path stopped there
    comes back with `cut` true, holding its finished steps, for the caller to drop: it is no
    pure function of its index, and its file would pass for a whole path on a resume.
    """
    # this process's clock from here: the wall clock may step meanwhile, the solver's does not
    deadline = None if stop_at is None else time.perf_counter() + (stop_at - time.time())
    rng = np.random.default_rng([spec.seed, index])
    g_region = sample_path_load(mesh, spec, rng)
    solver = _solver(mesh, material, rtol, max_newton)
    region = np.asarray(spec.region)
    forces, us, its = [], [], []
    u = None
    cut = False
    t0 = time.perf_counter()
    for step in range(1, spec.steps + 1):
        g = np.zeros((mesh.n_nodes, 3))
        g[region] = g_region * (step / spec.steps)
        res = solver.solve(g, u, deadline)
        if res.status == "time_limit":
            log.info("path %d: stopped at the data's end, at step %d of %d", index, step, spec.steps)
            cut = True
            break
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
        "cut": cut,
    }


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
    """Solve paths 0..n_paths-1 that are not on disk yet, in parallel; yields each as written
    (and those that `until` stopped, unwritten, with `cut` true).

    With `scheduler` the work goes to that Dask cluster; otherwise a LocalCluster of `workers`
    single-threaded processes (one per core: the factorisation is the hot spot and threads
    would only fight over it). With workers=0 it runs in this process (tests, debugging).
    `max_newton` caps each step's Newton iterations (solve_path); a data folder should hold
    paths of one cap (build.data_key). `until` (a time.perf_counter() value): the generation
    stops there, in this process before a path that the slowest so far says would end past it
    (path_fits), and a path still being solved then, here or in a worker (WORKER_STOP_EARLY_S
    before it), stops there too (solve_path's stop_at): it is yielded unwritten, with `cut` true (the generation's last
    here; with workers, those already finished may still come), and the rest in flight are
    dropped; local workers start only where the time to
    it pays for them (local_workers_pay), else the paths are solved in this process.
    Connecting to `scheduler`, and waiting for its first worker, each take at most Dask's connect
    timeout (distributed.comm.timeouts.connect), never past `until` where it is given, else
    `deadline` (a time.perf_counter() value: the build's end). Local workers that their
    nannies restart mid-build (killed: the OOM killer on a big mesh) are sent the mesh again and
    the paths in flight solved again, up to LOCAL_RESTARTS times; a cluster lost otherwise is a
    ClusterError that says how many paths the folder keeps. The temporaries that a build killed
    mid-write left in the folder are removed first, unless another build is writing there
    (pathfiles.writing).
    """
    data_dir = Path(data_dir)
    data_dir.mkdir(parents=True, exist_ok=True)
    with writing(data_dir):  # held by every build that writes here; a killed one's temporaries go first
        yield from _generate(
            mesh, material, spec, data_dir, n_paths, workers, scheduler, progress, max_newton, until, deadline
        )


def _generate(
    mesh: TetMesh,
    material: NeoHookean,
    spec: LoadSpec,
    data_dir: Path,
    n_paths: int,
    workers: int,
    scheduler: str | None,
    progress: bool,
    max_newton: int | None,
    until: float | None,
    deadline: float | None,
) -> Generator[dict, None, None]:
    """generate's work, in a folder held for writing."""
    listed = sorted(i for i in done_indices(data_dir) if i < n_paths)  # listed once, not once per path
    # a damaged file (cut short by a power cut, a stray one) is set aside and its path solved again
    on_disk = frozenset(intact_indices(data_dir, listed, len(spec.region), mesh.n_nodes, spec.steps))
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
    # the wall clock's reading of `until`: a worker's perf_counter is not this process's
    stop_at = None if until is None else time.time() + (until - time.perf_counter())
    if workers == 0 and scheduler is None:
        took: list[float] = []  # the solve seconds of this run's paths: what the next may take
        for i in todo:
            if not path_fits(until, took):  # none starts that its predecessors say would end past it
                break
            result = solve_path(mesh, material, spec, i, max_newton=max_newton, stop_at=stop_at)
            if result["cut"]:  # the clock stopped it: unwritten, its seconds for the refusal
                yield result
                break
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
    interrupted = False  # a Ctrl-C: the shutdown without distributed's log lines
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
            # the data share's end, not the build's: a scheduler found later leaves no time for paths
            _probe_scheduler(scheduler, _connect_seconds(until if until is not None else deadline))
        with _from_dask(scheduler):
            client = Client(scheduler or cluster)
            if scheduler is not None:
                _wait_for_workers(client, scheduler, _connect_seconds(until if until is not None else deadline), bar)
            sent = client.scatter([mesh, material, spec], broadcast=True)
            worker_stop = None if stop_at is None else stop_at - WORKER_STOP_EARLY_S
            pending: Iterator[int] = iter(todo)
            in_flight: dict = {}  # future -> its path's index, until written

            def submit(n: int) -> list:
                """The next n paths, in index order."""
                indices = list(itertools.islice(pending, n))
                futures = [
                    client.submit(solve_path, *sent, i, max_newton=max_newton, stop_at=worker_stop, pure=False)
                    for i in indices
                ]
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
                if not result["cut"]:  # a cut path: the clock has run out, so no more are sent
                    done.update(submit(more))
            in_flight.pop(fut, None)
            if not result["cut"]:  # a cut path is no whole one: never written
                write_path(data_dir, result)
                bar.update(1)
                bar.set_postfix(samples=_count(bar, result))
            fut.release()
            yield result
    except KeyboardInterrupt:
        interrupted = True
        raise
    finally:
        bar.close()
        with _interrupted_quietly(client, cluster is not None) if interrupted else contextlib.nullcontext():
            _close(client, cluster)


def _close(client, cluster) -> None:
    """Close a generation's client and its local cluster (either may be None)."""
    if client is not None:
        with _quiet("distributed.client"):  # a lost scheduler: its reconnect, cancelled, logs a traceback
            client.close()
    if cluster is not None:
        try:
            cluster.close()
        except Exception as exc:
            # dask's close can race the nannies restarting killed workers (a KeyError, seen under
            # load); the paths are on disk, and an error raised here would hide the one in flight
            log.warning("closing the local Dask workers: %s: %s", type(exc).__name__, exc)


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


def _progress(total: int, initial: int, enabled: bool):
    bar = need("tqdm.auto", "the trainer's progress bar").tqdm(
        total=total, initial=initial, desc="load paths", unit="path", disable=not enabled
    )
    bar.samples = 0
    return bar


def _count(bar, result: dict) -> int:
    bar.samples += len(result["forces"])
    return bar.samples

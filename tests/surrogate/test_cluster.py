"""`elastreg train --scheduler`: the same command on a Dask cluster. A real scheduler and a real
worker, separate processes on loopback, as a cluster's would be on other machines."""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from service.store import load_entry
from tests.conftest import write_bar_scene

pytest.importorskip("distributed")
ROOT = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def cluster(dask_processes):
    """The address of a scheduler with one worker, each a process of its own."""
    address, _ = dask_processes
    return address


@pytest.fixture
def dask_processes(tmp_path):
    """A scheduler and one worker, each a `dask` process: the address, and the two processes."""
    from distributed import Client

    dask = shutil.which("dask", path=str(Path(sys.executable).parent)) or shutil.which("dask")
    assert dask, "the dask command comes with distributed"
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    log = open(tmp_path / "cluster.log", "w")
    procs = [
        subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--dashboard-address", ":0"],
                         stdout=log, stderr=subprocess.STDOUT, env=env),
        subprocess.Popen([dask, "worker", address, "--nworkers", "1", "--nthreads", "1", "--memory-limit", "0",
                          "--local-directory", str(tmp_path / "worker")],
                         stdout=log, stderr=subprocess.STDOUT, env=env, cwd=ROOT),
    ]  # fmt: skip
    try:
        deadline = time.monotonic() + 90
        while True:  # the scheduler may not be listening yet
            try:
                with Client(address, timeout=5) as client:
                    client.wait_for_workers(1, timeout=60)
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)
        yield address, procs
    finally:
        for p in procs[::-1]:
            p.terminate()
        for p in procs:
            p.wait(timeout=30)
        log.close()


def tasks_run(address: str) -> dict:
    """What the scheduler has seen, by task prefix: {prefix: {state: count}}."""
    from distributed import Client

    def prefixes(dask_scheduler):
        return {k: dict(v.state_counts) for k, v in dask_scheduler.task_prefixes.items()}

    with Client(address, timeout=10) as client:
        return client.run_on_scheduler(prefixes)


def test_train_on_a_dask_cluster_makes_the_same_data_as_locally(tmp_path, bar, cluster):
    from service.build import build
    from service.scene import load_scene
    from service.surrogate.data import load_dataset

    scene_file = write_bar_scene(tmp_path / "scene", bar, samples=24)
    r = subprocess.run(
        [sys.executable, "-m", "service.cli", "train", str(scene_file), "--scheduler", cluster,
         "--store", str(tmp_path / "store"), "--data", str(tmp_path / "data"), "--hidden", "32", "--rank", "8"],
        capture_output=True, text=True, timeout=600, cwd=ROOT,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    entry = load_entry(tmp_path / "store" / "bar")  # a verified entry, from data the cluster made
    paths = entry.manifest["training"]["paths"]
    assert paths >= 2
    solved = tasks_run(cluster)["solve_path"]  # the scheduler ran the paths, not this process
    assert solved.get("memory", 0) + solved.get("released", 0) + solved.get("forgotten", 0) >= paths

    # the same paths solved in this process: the cluster changes where, not what
    local = build(load_scene(scene_file), tmp_path / "local-store", workers=0, data_root=tmp_path / "local",
                  progress=False, samples=24)  # fmt: skip
    (remote_dir,) = (tmp_path / "data").iterdir()
    (local_dir,) = (tmp_path / "local").iterdir()
    assert remote_dir.name == local_dir.name  # one data key: the same scene
    F1, U1, _ = load_dataset(remote_dir, list(range(paths)))
    F2, U2, _ = load_dataset(local_dir, list(range(local.paths)))
    np.testing.assert_array_equal(F1, F2)
    np.testing.assert_allclose(U1, U2, rtol=0, atol=1e-12)


def test_a_timed_build_on_a_dask_cluster_keeps_to_its_minutes(tmp_path, bar, cluster):
    """--minutes with --scheduler: the build stops asking the cluster for paths at its data share
    and writes its entry inside the budget; the paths still queued are given back."""
    scene_file = write_bar_scene(tmp_path / "scene", bar, samples=30_000)  # far too many
    t0 = time.perf_counter()
    r = subprocess.run(
        [sys.executable, "-m", "service.cli", "train", str(scene_file), "--scheduler", cluster, "--minutes", "0.5",
         "--store", str(tmp_path / "store"), "--data", str(tmp_path / "data"), "--hidden", "32", "--rank", "8"],
        capture_output=True, text=True, timeout=600, cwd=ROOT,
    )  # fmt: skip
    wall = time.perf_counter() - t0
    assert r.returncode == 0, r.stderr[-3000:]
    # 0.5, not less: the minutes count from the process's start (11 s of it under a load of 10)
    assert wall < 0.5 * 60 + 20  # the budget, plus a loaded machine
    entry = load_entry(tmp_path / "store" / "bar")
    assert entry.manifest["training"]["minutes"] == 0.5
    assert 2 <= entry.manifest["training"]["paths"] < 10_000


def test_generation_stops_at_its_deadline_with_paths_still_running(tmp_path, bar, cluster):
    """A timed build's data phase ends at its clock, not when the next path happens to finish:
    a long path (seconds on a big organ) must not carry the build past its minutes."""
    from service.fem.material import NeoHookean
    from service.surrogate.data import LoadSpec, done_indices, generate

    spec = LoadSpec(region=tuple(bar.free_surface_nodes.tolist()), max_force=20.0, patch_nodes=(2, 6))
    mat = NeoHookean(4500.0, 0.45)
    got = list(generate(bar, mat, spec, tmp_path / "d", 200, scheduler=cluster, progress=False,
                        until=time.perf_counter()))  # fmt: skip
    assert len(got) == len(done_indices(tmp_path / "d")) < 200


def lost_cluster(exc: BaseException, where: str, data_dir: Path) -> int:
    """The paths a lost cluster's ClusterError says the folder keeps, checked against the folder."""
    from service.surrogate.data import done_indices, load_dataset

    message = str(exc)
    assert "\n" not in message, message
    match = re.fullmatch(
        rf"lost {re.escape(where)} mid-build \((.+)\): (\d+) load paths kept in {re.escape(str(data_dir))}; "
        r"the same command resumes",
        message,
    )
    assert match, message
    kept = int(match.group(2))
    assert kept == len(done_indices(data_dir))
    load_dataset(data_dir)  # whole files: each one read back
    return kept


def test_a_scheduler_killed_mid_build_is_one_line_that_keeps_the_paths(tmp_path, bar, dask_processes):
    """The scheduler's process killed while paths are solved: a ClusterError of one line that
    names the cluster and the paths the folder keeps (the same command resumes from them)."""
    from service.fem.material import NeoHookean
    from service.surrogate.cluster import ClusterError
    from service.surrogate.data import LoadSpec, generate

    address, (scheduler, _) = dask_processes
    spec = LoadSpec(region=tuple(bar.free_surface_nodes.tolist()), max_force=20.0, patch_nodes=(2, 6))
    paths = generate(bar, NeoHookean(4500.0, 0.45), spec, tmp_path / "d", 10_000, scheduler=address, progress=False)
    got = [next(paths), next(paths)]
    scheduler.kill()
    scheduler.wait(timeout=30)
    t0 = time.perf_counter()
    with pytest.raises(ClusterError) as caught:
        got.extend(paths)
    assert time.perf_counter() - t0 < 60  # not Dask's reconnect timeouts, one after another
    assert lost_cluster(caught.value, f"the Dask cluster at {address}", tmp_path / "d") >= len(got) >= 2


def local_workers() -> list:
    """This process's Dask worker processes (a LocalCluster's nannies spawn them)."""
    import psutil

    return [p for p in psutil.Process().children(recursive=True) if "spawn_main" in " ".join(p.cmdline())]


@pytest.mark.slow  # 13 s: four starts of a local worker
def test_local_workers_killed_once_too_often_end_the_build_in_one_line(tmp_path, bar, caplog):
    """Local workers killed (the OOM killer) are restarted by their nannies and sent the mesh
    again LOCAL_RESTARTS times; killed once more, the build ends in one line that says how many
    paths the folder keeps."""
    from service.fem.material import NeoHookean
    from service.surrogate.cluster import LOCAL_RESTARTS, ClusterError
    from service.surrogate.data import LoadSpec, generate

    spec = LoadSpec(region=tuple(bar.free_surface_nodes.tolist()), max_force=20.0, patch_nodes=(2, 6))
    paths = generate(bar, NeoHookean(4500.0, 0.45), spec, tmp_path / "d", 10_000, workers=1, progress=False)
    got, kills = [], 0
    with pytest.raises(ClusterError) as caught:
        for result in paths:  # each path back: kill the worker while the next ones are in flight
            got.append(result)
            workers = local_workers()
            assert len(workers) == 1
            for worker in workers:
                worker.kill()
            kills += 1
    assert kills == LOCAL_RESTARTS + 1
    restarted = [r for r in caplog.records if "the local Dask workers restarted" in r.getMessage()]
    assert len(restarted) == LOCAL_RESTARTS
    assert lost_cluster(caught.value, "the local Dask workers", tmp_path / "d") >= len(got) == kills

"""The build-minutes curve: ``elastreg train SCENE --minutes M`` from nothing, scored on one
held-out test set per scene.

Each (scene, minutes) pair builds from an empty data folder into a scratch store, so the clock
covers the whole build (FEM data and training). A build's own validation paths are a share of
what its budget bought, so they differ from build to build (a few dozen samples on a slow
mesh): every build is also scored on one test set per scene, the same for every budget, drawn
from the scene's load distribution with a seed no build uses (TEST_SEED) and kept on disk. Rows
accumulate over runs (a rerun of a pair at the same commit replaces its row; rows of other
commits stay as history), each stamped with its machine, commit, load average and test set (its
size and a hash of its loads); a curve shows only rows of one machine and one test set.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import os
import shlex
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..build import build, data_key, load_spec
from ..fem.material import NeoHookean
from ..network_size import FEATURES, WEIGHT_DECAY
from ..optional import need
from ..scene import Scene
from ..store import load_entry
from ..surrogate.data import done_indices, generate, load_dataset
from ..surrogate.train import TrainConfig, nodal_errors
from . import machine

#: the test paths' seed: builds draw theirs from the scene's seed (0 in every benchmark scene)
TEST_SEED = 7919
#: the issue's aim: median relative error after 10 minutes on a 1-3k-node organ
AIM_RELATIVE = 0.10

#: rows before the physics layout (commit de1d114) had only the skip flag: the skip path then
#: lay inside the POD basis
_LAYOUT = {True: "physics", False: "raw"}


def layout_of(row: dict) -> str:
    return row.get("layout") or ("basis-skip" if row.get("physics_skip") else "raw")


def scene_argument(scene: Scene) -> str:
    """What `elastreg train` takes for this scene: its file, resolved, or a builtin's name (a
    kept entry's rebuild command named `NAME.toml`, a file there seldom was)."""
    origin = scene.origin
    return origin.removeprefix("builtin:") if origin.startswith("builtin:") else os.path.realpath(origin)


def test_set(scene: Scene, paths: int, root: Path, workers: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The scene's held-out test loads (B, k, 3) on its region (k,) and displacements (B, n, 3),
    solved once and kept under `root`."""
    mesh, loaded = scene.build_mesh()
    region = scene.region_nodes(mesh, loaded)
    material = NeoHookean.of(scene.material)
    spec = dataclasses.replace(load_spec(scene, mesh, loaded), seed=TEST_SEED)
    folder = root / f"{scene.name}-{data_key(mesh.hash, material, spec)}"
    for _ in generate(mesh, material, spec, folder, paths, workers=workers, progress=False):
        pass
    F, U, _ = load_dataset(folder, sorted(i for i in done_indices(folder) if i < paths))
    return F, U, region


def loads_hash(F: np.ndarray) -> str:
    """A short hash of a test set's loads: rows scored on other loads (another --test-paths, a
    test set solved anew) are not points of one curve."""
    return hashlib.sha256(np.ascontiguousarray(F, np.float64).tobytes()).hexdigest()[:12]


def score(entry_dir: Path, F: np.ndarray, U: np.ndarray, region: np.ndarray) -> dict:
    """Mean and p95 nodal error (mm), mean and median relative error of an entry on a test set,
    with linear physics alone on the same loads beside them."""
    model = load_entry(entry_dir).network
    pred = np.concatenate([model.predict(F[i : i + 256], region) for i in range(0, len(F), 256)])
    pred, true = pred.reshape(len(pred), -1), U.reshape(len(U), -1).astype(np.float64)
    e = nodal_errors(pred, true)
    size = np.maximum(np.linalg.norm(true, axis=1), 1e-12)
    linear = model.compliance().displacements(F, region)
    rel = np.linalg.norm(pred - true, axis=1) / size
    rel_linear = np.linalg.norm(linear - true, axis=1) / size
    return {
        "test_samples": len(F),
        "test_seed": TEST_SEED,
        "test_loads": loads_hash(F),
        "test_mean_mm": float(e.mean() * 1e3),
        "test_p95_mm": float(np.percentile(e, 95) * 1e3),
        "test_relative": float(rel.mean()),
        "test_relative_median": float(np.median(rel)),
        "test_zero_mean_mm": float(np.linalg.norm(U, axis=-1).mean() * 1e3),
        "test_linear_mean_mm": float(nodal_errors(linear, true).mean() * 1e3),
        "test_linear_relative": float(rel_linear.mean()),
        "test_linear_relative_median": float(np.median(rel_linear)),
    }


@contextlib.contextmanager
def as_train_runs(threads: int | None = None) -> Iterator[int]:
    """torch's and BLAS's threads as `elastreg train` has them, a thread a core (or `threads`),
    for a build's length; yields torch's count. The bench runs at the server's one thread a
    solve, which timed every build's training on one core of two."""
    import torch

    before, n = torch.get_num_threads(), threads or machine.cores()
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # BLAS as the environment left it
        blas: contextlib.AbstractContextManager = contextlib.nullcontext()
    else:
        blas = threadpool_limits(limits=n)
    torch.set_num_threads(n)
    try:
        with blas:
            yield torch.get_num_threads()
    finally:
        torch.set_num_threads(before)


def timed_build(
    scene: Scene,
    minutes: float,
    test: tuple,
    workers: int,
    physics_skip: bool = True,
    keep: Path | None = None,
    config: TrainConfig | None = None,
    threads: int | None = None,
) -> dict:
    """One build of `scene` within `minutes` from an empty data folder, and its row. The entry
    goes to the store `keep` when given (for the other parts to use), else it is discarded.
    `config` (default: the defaults, with `physics_skip`) and `threads` (training's; default a
    core each) let a study build other settings the same way (benchmarks/settings_build.py)."""
    config = config or TrainConfig(physics_skip=physics_skip)
    stamp = machine.describe()
    started = time.strftime("%Y-%m-%d %H:%M:%S")
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        load0 = os.getloadavg()[0]
        store = keep if keep is not None else Path(tmp) / "store"
        command = f"elastreg train {shlex.quote(scene_argument(scene))} --minutes {minutes:g}"
        if (config.features, config.weight_decay) != (FEATURES, WEIGHT_DECAY):
            command += f" --features {config.features} --weight-decay {config.weight_decay:g}"
        with as_train_runs(threads) as trained_on:
            report = build(scene, store, workers=workers, data_root=Path(tmp) / "data", progress=False,
                           minutes=minutes, config=config, replace=True, command=command)  # fmt: skip
        wall = time.perf_counter() - t0
        tested = score(store / scene.name, *test)
    m = report.metrics
    return {
        "scene": scene.name,
        "minutes": minutes,
        "physics_skip": config.physics_skip,
        "layout": _LAYOUT[config.physics_skip],
        "features": config.features,
        "weight_decay": config.weight_decay,
        "commit": stamp["commit"],
        "cpu": stamp["cpu"],
        "started": started,
        "wall_s": round(wall, 1),
        "samples": report.samples,
        "paths": report.paths,
        "data_s": round(report.data_seconds, 1),
        "train_s": round(report.train_seconds, 1),
        "train_threads": trained_on,  # rows without it trained on one (the bench's setting)
        "epochs": m["epochs"],
        "val_mean_mm": m["mean_mm"],
        "val_p95_mm": m["p95_mm"],
        "val_relative": m.get("relative"),
        "zero_mean_mm": m["zero_mean_mm"],
        "linear_mean_mm": m.get("linear_mean_mm"),
        **tested,
        "load_before": load0,
        "load_after": os.getloadavg()[0],
    }


def merge(rows: list[dict], row: dict) -> list[dict]:
    """`row` replaces a row of the same scene, minutes, layout and commit; the rest stay."""

    def key(r: dict) -> tuple:
        return r["scene"], r["minutes"], layout_of(r), r.get("commit")

    return [r for r in rows if key(r) != key(row)] + [row]


def minutes_part(
    scenes: list[Scene],
    minutes: list[float],
    *,
    previous: list[dict] | None = None,
    test_paths: int = 40,
    test_data: Path,
    workers: int = 2,
    physics_skip: bool = True,
    keep: Path | None = None,
    on_row=None,
    built: frozenset[tuple[str, float]] = frozenset(),
) -> dict:
    """Build every scene at every budget but the (scene, minutes) pairs `built` (a stopped run's,
    resumed); the rows, after `previous` (earlier runs' rows)."""
    rows = list(previous or [])
    for scene in scenes:
        todo = [m for m in minutes if (scene.name, m) not in built]
        if not todo:  # nor its test set, which takes FEM solves
            continue
        test = test_set(scene, test_paths, test_data, workers)
        for m in todo:
            rows = merge(rows, timed_build(scene, m, test, workers, physics_skip, keep))
            if on_row is not None:  # a long run keeps what it has made
                on_row(rows)
    return {"rows": rows}


def comparable(row: dict) -> tuple:
    """What a curve's points share: the machine and the test set (its size and its loads' hash;
    None in rows from before they were recorded, comparable with none but their own kind)."""
    return row.get("cpu"), row.get("test_samples"), row.get("test_loads")


def _newest(rows: list[dict]) -> dict[tuple, dict]:
    """The newest row of each scene and budget, in the physics layout and scored on the test set."""
    best: dict[tuple, dict] = {}
    for r in rows:
        if layout_of(r) == "physics" and "test_relative" in r:
            k = (r["scene"], r["minutes"])
            if k not in best or r["started"] > best[k]["started"]:
                best[k] = r
    return best


def latest(rows: list[dict]) -> list[dict]:
    """The newest row of each scene and budget (physics layout, scored on the test set) that was
    built on the machine and scored on the test set of its scene's newest row: one curve, one
    machine and the same loads for every budget (the others are :func:`left_out`)."""
    best = _newest(rows)
    newest: dict[str, dict] = {}
    for r in best.values():
        if r["scene"] not in newest or r["started"] > newest[r["scene"]]["started"]:
            newest[r["scene"]] = r
    kept = [r for r in best.values() if comparable(r) == comparable(newest[r["scene"]])]
    return sorted(kept, key=lambda r: (r["scene"], r["minutes"]))


def left_out(rows: list[dict]) -> list[dict]:
    """The newest rows of a scene and budget that :func:`latest` leaves out: built on another
    machine or scored on another test set than their scene's newest row."""
    shown = latest(rows)
    return sorted((r for r in _newest(rows).values() if r not in shown), key=lambda r: (r["scene"], r["minutes"]))


def plot(rows: list[dict], path: Path) -> None:
    """Test-set relative error against build minutes, per scene, linear physics alone dashed."""
    matplotlib = need("matplotlib", "the benchmark's figures")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8.4, 4.2))
    for i, scene in enumerate(dict.fromkeys(r["scene"] for r in rows)):
        rs = [r for r in rows if r["scene"] == scene]
        colour = f"C{i}"
        x = [r["minutes"] for r in rs]
        ax.plot(x, [r["test_relative"] for r in rs], "o-", color=colour, label=f"{scene}: mean")
        med = [r for r in rs if "test_relative_median" in r]
        if med:
            ax.plot([r["minutes"] for r in med], [r["test_relative_median"] for r in med], "s", mfc="none",
                    color=colour, label=f"{scene}: median")  # fmt: skip
        ax.axhline(
            rs[-1]["test_linear_relative"], ls="--", lw=1, color=colour, label=f"{scene}: linear physics alone, mean"
        )
        lin_med = [r["test_linear_relative_median"] for r in rs if "test_linear_relative_median" in r]
        if lin_med:
            ax.axhline(lin_med[-1], ls="-.", lw=0.8, color=colour, label=f"{scene}: linear physics alone, median")
    ax.axhline(AIM_RELATIVE, ls=":", color="k", label="aim at 10 minutes")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xticks([5, 10, 30, 60], labels=["5", "10", "30", "60"])
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel("build minutes (whole build, 2 workers)")
    ax.set_ylabel("relative error on the held-out test set")
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

"""Validation error against build minutes: `elastreg train SCENE --minutes M` from nothing.

Each (scene, minutes) pair builds from an empty data folder into a scratch store, so the clock
covers the whole build (FEM data and training), and records the manifest's validation figures
(mean and p95 nodal error, relative error: mean error over mean displacement) beside the samples
the budget bought. Each build's own validation paths are a share of what its budget bought, so
they differ from build to build (a few dozen samples on a slow mesh): every build is also scored
on one held-out test set per scene, the same for every budget, drawn from the scene's load
distribution with a seed no build uses (TEST_SEED) and kept on disk (--test-data). The artefact
names the machine, the commit and the load average, since the 2 cores may be shared.

    python benchmarks/build_minutes.py --minutes 5 10 --scenes liver_sofa liver_deepphysx
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.bench.machine import describe
from service.build import build, data_key, load_spec
from service.fem.material import NeoHookean
from service.scene import Scene, load_scene
from service.store import load_entry
from service.surrogate.data import done_indices, generate, load_dataset
from service.surrogate.train import TrainConfig, nodal_errors

#: the test paths' seed: builds draw theirs from the scene's seed (0 in every benchmark scene)
TEST_SEED = 7919

#: rows before the physics layout (commit de1d114) had only the skip flag: the skip path then
#: lay inside the POD basis
_LAYOUT = {True: "physics", False: "raw"}


def layout_of(row: dict) -> str:
    return row.get("layout") or ("basis-skip" if row.get("physics_skip") else "raw")


def test_set(scene: Scene, paths: int, root: Path, workers: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The scene's held-out test loads (B, k, 3) on its region (k,) and displacements (B, n, 3),
    solved once and kept under `root`."""
    mesh, loaded = scene.build_mesh()
    region = scene.region_nodes(mesh, loaded)
    material = NeoHookean(float(scene.material.E), float(scene.material.nu))
    spec = dataclasses.replace(load_spec(scene, region), seed=TEST_SEED)
    folder = root / f"{scene.name}-{data_key(mesh.hash, material, spec)}"
    for _ in generate(mesh, material, spec, folder, paths, workers=workers, progress=False):
        pass
    F, U, _ = load_dataset(folder, sorted(i for i in done_indices(folder) if i < paths))
    return F, U, region


def score(entry_dir: Path, F: np.ndarray, U: np.ndarray, region: np.ndarray) -> dict:
    """Mean and p95 nodal error (mm), mean and median relative error of an entry on a test set."""
    model = load_entry(entry_dir).network
    pred = np.concatenate([model.predict(F[i : i + 256], region) for i in range(0, len(F), 256)])
    pred, true = pred.reshape(len(pred), -1), U.reshape(len(U), -1).astype(np.float64)
    e = nodal_errors(pred, true)
    size = np.maximum(np.linalg.norm(true, axis=1), 1e-12)
    linear = model.compliance().displacements(F, region)  # the same loads, linear physics alone
    rel = np.linalg.norm(pred - true, axis=1) / size
    rel_linear = np.linalg.norm(linear - true, axis=1) / size
    return {
        "test_samples": len(F),
        "test_seed": TEST_SEED,
        "test_mean_mm": float(e.mean() * 1e3),
        "test_p95_mm": float(np.percentile(e, 95) * 1e3),
        "test_relative": float(rel.mean()),
        "test_relative_median": float(np.median(rel)),  # the aim is on the median
        "test_zero_mean_mm": float(np.linalg.norm(U, axis=-1).mean() * 1e3),
        "test_linear_mean_mm": float(nodal_errors(linear, true).mean() * 1e3),
        "test_linear_relative": float(rel_linear.mean()),
        "test_linear_relative_median": float(np.median(rel_linear)),
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--minutes", type=float, nargs="+", default=[5.0, 10.0])
    p.add_argument("--scenes", nargs="+", default=["liver_sofa", "liver_deepphysx"])
    p.add_argument("--workers", type=int, default=2)
    p.add_argument(
        "--physics-skip",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="the physics layout (elastreg train's default); --no-physics-skip: the raw-force network",
    )
    p.add_argument("--out", default=str(ROOT / "reports" / "build-minutes" / "build_minutes.json"))
    p.add_argument("--test-paths", type=int, default=40, help="held-out test paths per scene (5 samples each)")
    p.add_argument("--test-data", default=str(Path.home() / ".cache" / "elastreg" / "test-data"))
    args = p.parse_args()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rows = json.loads(out.read_text())["rows"] if out.exists() else []
    for name in args.scenes:
        scene = load_scene(ROOT / "benchmarks" / "scenes" / f"{name}.toml")
        F_test, U_test, region = test_set(scene, args.test_paths, Path(args.test_data), args.workers)
        for minutes in args.minutes:
            machine = describe()
            started = time.strftime("%Y-%m-%d %H:%M:%S")
            with tempfile.TemporaryDirectory() as tmp:
                t0 = time.perf_counter()
                load0 = os.getloadavg()[0]
                report = build(
                    scene,
                    Path(tmp) / "store",
                    workers=args.workers,
                    data_root=Path(tmp) / "data",
                    progress=False,
                    minutes=minutes,
                    config=TrainConfig(physics_skip=args.physics_skip),
                )
                wall = time.perf_counter() - t0
                tested = score(Path(tmp) / "store" / scene.name, F_test, U_test, region)
            m = report.metrics
            row = {
                "scene": name,
                "minutes": minutes,
                "physics_skip": args.physics_skip,
                "layout": _LAYOUT[args.physics_skip],
                "commit": machine["commit"],
                "started": started,
                "wall_s": round(wall, 1),
                "samples": report.samples,
                "paths": report.paths,
                "data_s": round(report.data_seconds, 1),
                "train_s": round(report.train_seconds, 1),
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
            # a rerun at the same commit replaces its row; rows of other commits are history
            key = (name, minutes, row["layout"], row["commit"])
            rows = [r for r in rows if (r["scene"], r["minutes"], layout_of(r), r.get("commit")) != key] + [row]
            print(json.dumps(row), flush=True)
            out.write_text(json.dumps({"machine": machine, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""One timed build of a scene with training settings of its own, scored as `elastreg bench minutes`
scores its rows: the build-minutes path (its plan, its data, its test set) with --features and
--weight-decay given, so that two settings can be built the same way and compared.

`bench minutes` builds at the defaults; session 31's 60-minute liver row trained on one thread
(the bench's, before 169f5ea), so --threads sets the training's threads to compare with it.

    python benchmarks/settings_build.py benchmarks/scenes/liver_paper.toml --minutes 60 \\
        --features 256 --weight-decay 0 --threads 1 --store STORE --data DATA \\
        --out reports/settings-s32/old_settings_build_row.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.bench import machine
from service.bench import minutes as M
from service.build import build
from service.config import flush_subnormals, limit_threads
from service.scene import load_scene
from service.surrogate.train import TrainConfig


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene")
    p.add_argument("--minutes", type=float, required=True)
    p.add_argument("--features", type=int, required=True)
    p.add_argument("--weight-decay", type=float, required=True)
    p.add_argument("--threads", type=int, default=machine.cores(), help="training threads (default: a core each)")
    p.add_argument("--store", type=Path, required=True, help="where the entry is kept")
    p.add_argument("--data", type=Path, required=True, help="an empty data folder: the clock covers the FEM")
    p.add_argument("--test-data", type=Path, default=Path.home() / ".cache" / "elastreg" / "test-data")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    flush_subnormals()  # before torch's threads, as elastreg train
    limit_threads(args.threads)
    scene = load_scene(args.scene)
    stamp, started, load0 = machine.describe(), time.strftime("%Y-%m-%d %H:%M:%S"), os.getloadavg()[0]
    command = (
        f"elastreg train {args.scene} --minutes {args.minutes:g} --features {args.features} "
        f"--weight-decay {args.weight_decay:g}"
    )
    config = TrainConfig(physics_skip=True, features=args.features, weight_decay=args.weight_decay)
    t0 = time.perf_counter()
    report = build(scene, args.store, workers=2, data_root=args.data, progress=False, minutes=args.minutes,
                   config=config, replace=True, command=command)  # fmt: skip
    wall = time.perf_counter() - t0
    tested = M.score(args.store / scene.name, *M.test_set(scene, 40, args.test_data, 2))
    m = report.metrics
    row = {
        "scene": scene.name,
        "minutes": args.minutes,
        "layout": "physics",
        "features": args.features,
        "weight_decay": args.weight_decay,
        "train_threads": args.threads,
        "commit": stamp["commit"],
        "cpu": stamp["cpu"],
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
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(row, indent=1))
    print(json.dumps(row, indent=1))
    return 0


if __name__ == "__main__":  # Dask's workers import this module: the build runs only here
    raise SystemExit(main())

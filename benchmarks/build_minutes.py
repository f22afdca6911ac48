"""Validation error against build minutes: `elastreg train SCENE --minutes M` from nothing.

Each (scene, minutes) pair builds from an empty data folder into a scratch store, so the clock
covers the whole build (FEM data and training), and records the manifest's validation figures
(mean and p95 nodal error, relative error: mean error over mean displacement) beside the samples
the budget bought. The artefact names the machine, the commit and the load average, since the
2 cores may be shared.

    python benchmarks/build_minutes.py --minutes 5 10 --scenes liver_sofa liver_deepphysx
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.bench.machine import describe
from service.build import build
from service.scene import load_scene
from service.surrogate.train import TrainConfig

#: rows before the physics layout (commit de1d114) had only the skip flag: the skip path then
#: lay inside the POD basis
_LAYOUT = {True: "physics", False: "raw"}


def layout_of(row: dict) -> str:
    return row.get("layout") or ("basis-skip" if row.get("physics_skip") else "raw")


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
    args = p.parse_args()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rows = json.loads(out.read_text())["rows"] if out.exists() else []
    for name in args.scenes:
        scene = load_scene(ROOT / "benchmarks" / "scenes" / f"{name}.toml")
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
                "load_before": load0,
                "load_after": os.getloadavg()[0],
            }
            key = (name, minutes, row["layout"])
            rows = [r for r in rows if (r["scene"], r["minutes"], layout_of(r)) != key] + [row]
            print(json.dumps(row), flush=True)
            out.write_text(json.dumps({"machine": machine, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

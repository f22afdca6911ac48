"""Where a timed build's FEM time goes: each training load path's Newton iterations per step,
seconds, kept steps and largest displacement, for the first paths of a scene (its own seed, the
paths a build solves first; never the build-minutes test set's).

    python benchmarks/path_cost.py benchmarks/scenes/liver_sofa.toml --paths 12 [--max-newton 24]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.bench.machine import describe
from service.build import load_spec
from service.config import limit_threads
from service.fem.material import NeoHookean
from service.scene import load_scene
from service.surrogate.data import solve_path


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenes", nargs="+")
    p.add_argument("--paths", type=int, default=12)
    p.add_argument(
        "--max-newton", type=int, default=None, help="cap each step's Newton iterations (a timed build's cap)"
    )
    p.add_argument("--out", default=str(ROOT / "reports" / "path-cost" / "path_cost.json"))
    args = p.parse_args()
    limit_threads(1)  # one worker's view: a build runs one single-threaded process per core
    result: dict = {"machine": describe(), "scenes": {}}
    for path in args.scenes:
        scene = load_scene(path)
        mesh, loaded = scene.build_mesh()
        material = NeoHookean.of(scene.material)
        spec = load_spec(scene, mesh, loaded)
        solve_path(mesh, material, spec, args.paths + 1, max_newton=args.max_newton)  # compile and warm, not counted
        rows = []
        for i in range(args.paths):
            r = solve_path(mesh, material, spec, i, max_newton=args.max_newton)
            kept = len(r["forces"])
            umax = float(np.linalg.norm(r["u"][-1], axis=1).max() * 1e3) if kept else 0.0
            rows.append(
                {
                    "path": i,
                    "kept_steps": kept,
                    "steps": spec.steps,
                    "seconds": round(r["seconds"], 2),
                    "newton_iterations": r["newton_iterations"].tolist(),
                    "max_displacement_mm": round(umax, 1),
                }
            )
            print(
                f"{scene.name} path {i:2d}: {kept}/{spec.steps} steps, iterations {rows[-1]['newton_iterations']}, "
                f"{r['seconds']:.2f} s, largest displacement {umax:.1f} mm",
                flush=True,
            )
        seconds = np.array([r["seconds"] for r in rows])
        failed = [r for r in rows if r["kept_steps"] < r["steps"]]
        summary = {
            "paths": len(rows),
            "seconds_per_path": float(seconds.mean()),
            "samples_per_second": sum(r["kept_steps"] for r in rows) / float(seconds.sum()),
            "failed_paths": len(failed),
            "failed_share_of_time": sum(r["seconds"] for r in failed) / float(seconds.sum()),
        }
        print(f"{scene.name}: {json.dumps(summary)}", flush=True)
        result["scenes"][scene.name] = {"max_newton": args.max_newton, "rows": rows, "summary": summary}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

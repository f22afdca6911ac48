"""The demo's stream at other seeds, in process: how far the force error of `elastreg demo` is the
clouds' noise, and how far the model's.

The demo's sequence (its tool, support, 0.7 of the model's training force, 1,000 points, 0.5 mm
of noise) at seeds 0-5 (the demo runs seed 0), registered by the network and by the Newton
method with the session settings the demo uses (its noise declared, choosing alpha). Prints
and writes, per method and seed, the median force error and registration error over the frames,
how the error estimate stood to the error (median and smallest ratio, rank correlation), and
how the force error splits: the net force's component along the true one (under 100 %: the
prior's shrinkage, a bias) and its part across it (the cloud's noise, frame by frame).
`--alpha` runs fixed weights (the noise then informs the estimate alone) beside or instead of
the demo's choice (`noise`); `--methods network` leaves the Newton method out.

    python benchmarks/demo_seeds.py [--store model_store] [--seeds 0 1 2 3 4 5] [--alpha noise 1e-6 ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from clients.demo import spearman
from service.bench.cases import run_case, synthetic_case
from service.bench.machine import describe
from service.config import limit_threads
from service.demo import NOISE, PEAK_FRACTION, patches, session_settings
from service.registration.settings import SessionConfig
from service.store import load_entry


def _weight(text: str) -> float | None:
    """A fixed alpha, or None for 'noise': the demo's own choice."""
    return None if text == "noise" else float(text)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", default=str(ROOT / "model_store"))
    p.add_argument("--model", default="phantom")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4, 5])
    p.add_argument("--alpha", type=_weight, nargs="+", default=[None], help="'noise' (the demo's choice) or a weight")
    p.add_argument("--methods", nargs="+", default=["network", "fem"], choices=["network", "fem"])
    p.add_argument("--out", default=str(ROOT / "reports" / "demo" / "demo_seeds.json"))
    args = p.parse_args()
    limit_threads(1)
    entry = load_entry(Path(args.store) / args.model)
    tool, support = patches(entry.mesh, entry.region)
    peak = PEAK_FRACTION * entry.manifest["training"]["load_distribution"]["max_force"]
    rows = []
    for seed in args.seeds:
        case = synthetic_case(
            f"demo seed {seed}", entry.mesh, entry.fem.material, tool, support,
            frames=20, peak_force=peak, n_points=1000, seed=seed, noise=NOISE,
        )  # fmt: skip
        demo = SessionConfig(**session_settings(NOISE))  # the demo's session
        for method, alpha in itertools.product(args.methods, args.alpha):
            config = dataclasses.replace(demo, method=method, alpha=alpha)
            records = run_case(entry.model(method), case, config)
            error = np.array([r.tre_mm for r in records])
            estimate = np.array([r.error_estimate_mm for r in records], float)
            force = np.array([r.force_error_pct for r in records])
            along = np.array([r.force_along_pct for r in records], float)
            row = {
                "seed": seed,
                "method": method,
                "alpha": "the demo's (its noise)" if alpha is None else alpha,
                "frames": len(records),
                "force_error_pct_median": float(np.median(force)),
                "force_along_pct_median": float(np.median(along)),
                "force_across_pct_median": float(np.median(np.sqrt(np.maximum(force**2 - (along - 100) ** 2, 0)))),
                "registration_error_mm_median": float(np.median(error)),
                "estimate_mm_median": float(np.median(estimate)),
                "estimate_over_error_median": float(np.median(estimate / error)),
                "estimate_over_error_min": float(np.min(estimate / error)),
                "estimate_spearman": spearman(estimate.tolist(), error.tolist()),
            }
            rows.append(row)
            print(json.dumps(row), flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    summary = {"machine": describe(), "model": args.model, "seeds": args.seeds, "rows": rows}
    Path(args.out).write_text(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

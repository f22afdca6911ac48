"""How honest the error estimate is where the cloud determines little, on calibration sites.

The any-site cases of a model at CALIBRATION_SEED (no report uses them), registered twice: with
the whole cloud the camera sees (the benchmark's view), and with only its fifth farthest from
the tool's support (a view away from the tool, which says little of its force). Per method
(the Newton method and the network, both Levenberg-Marquardt as the any-site part runs them):
Spearman's rho between estimate and true error, the share of frames whose estimate is under half
their error, the median and least estimate / error. Run it in any checkout (`--checkout`) to
compare code over the same sites.

    python benchmarks/estimate_views.py --model STORE/liver_paper --sites 3 --frames 5 \\
        --out reports/estimate-prior/views_liver.json [--checkout OLD_CHECKOUT] [--support region]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", type=Path, required=True)
    p.add_argument("--sites", type=int, default=3)
    p.add_argument("--frames", type=int, default=5)
    p.add_argument("--checkout", type=Path, default=ROOT, help="the code to run (default: this one)")
    p.add_argument(
        "--support", choices=("patch", "region"), default="patch",
        help="each case's support (default), or the model's whole load region (a session's default; "
        "the Newton method then runs L-BFGS-B: Levenberg-Marquardt takes 500 nodes at most)",
    )  # fmt: skip
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    sys.path.insert(0, str(args.checkout.resolve()))
    from scipy.stats import spearmanr

    from service.bench.anysite import CALIBRATION_SEED, FEM, NETWORK_LM, anysite_cases
    from service.bench.cases import run_case
    from service.bench.machine import describe
    from service.store import load_entry

    entry = load_entry(args.model)
    fem_config = FEM if args.support == "patch" else dataclasses.replace(FEM, optimizer="lbfgsb")
    rows = []
    for case in anysite_cases(entry, sites=args.sites, frames=args.frames, seed=CALIBRATION_SEED):
        centre = case.mesh.nodes[case.support].mean(axis=0)  # the tool's patch and its margin
        if args.support == "region":
            case = dataclasses.replace(case, support=np.sort(entry.region))
        far = []
        for cloud in case.clouds:
            d = np.linalg.norm(cloud - centre, axis=1)
            far.append(cloud[d >= np.quantile(d, 0.8)])
        for view, c in (("whole", case), ("far", case.with_clouds(far, f"{case.name}, far view"))):
            for model, config, method in ((entry.fem, fem_config, "fem"), (entry.network, NETWORK_LM, "network-lm")):
                for r in run_case(model, c, config):
                    rows.append({"case": case.name, "view": view, "method": method, "frame": r.frame,
                                 "tre_mm": r.tre_mm, "estimate_mm": r.error_estimate_mm})  # fmt: skip
                    print(json.dumps(rows[-1]), flush=True)
    summary = {}
    for view in ("whole", "far", "both"):
        for method in ("fem", "network-lm"):
            rr = [r for r in rows if r["method"] == method and view in ("both", r["view"])]
            rr = [r for r in rr if np.isfinite(r["tre_mm"]) and np.isfinite(r["estimate_mm"])]
            t, s = np.array([r["tre_mm"] for r in rr]), np.array([r["estimate_mm"] for r in rr])
            summary[f"{view}, {method}"] = {
                "frames": len(rr),
                "spearman": float(spearmanr(t, s)[0]),
                "under_half": float(np.mean(s < 0.5 * t)),
                "median_ratio": float(np.median(s / t)),
                "least_ratio": float(np.min(s / t)),
            }
    print(json.dumps(summary, indent=1))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    record = {
        "machine": describe(),
        "model": args.model.name,
        "support": args.support,
        "summary": summary,
        "rows": rows,
    }
    args.out.write_text(json.dumps(record, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

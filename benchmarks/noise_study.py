"""Noisy clouds on the paper's liver: the default alpha against the `noise` setting.

    python benchmarks/noise_study.py [--store model_store] [--model liver_paper] [--method network]
                                     [--noise 0.5 1 2] [--frames 20] [--out reports/latest]

Every cloud of the paper's recorded sequence and of our own three (``elastreg bench liver``'s)
gets Gaussian noise of the given per-axis standard deviations (mm); each sequence is streamed
through one session with the default alpha, with its true noise given, and with twice its
noise given (an overstated sensor spec). Prints mean TRE, mean resultant-force error, median
milliseconds per warm frame and the median alpha of the later frames; writes noise.csv.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
from pathlib import Path

import numpy as np

from service.bench.cases import Case, liver_paper_case, noisy, run_case, summarise
from service.bench.liver import FEM, FEM_BUDGET_MS, NETWORK, own_sequences
from service.config import limit_threads
from service.store import load_entry


def stream(model, case: Case, config) -> dict:
    """One session over the case: mean TRE and force error, median warm ms, and the alpha the
    later frames ran with."""
    records = run_case(model, case, config)
    s = summarise(records)
    return {
        "tre_mm": s["tre_mean_mm"],
        "force_error_pct": s["force_error_mean_pct"],
        "ms": s["ms_median"],
        "alpha": float(np.median([r.alpha for r in records[len(records) // 4 :]])),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--store", default="model_store")
    p.add_argument("--model", default="liver_paper")
    p.add_argument("--method", choices=("network", "fem"), default="network")
    p.add_argument("--noise", type=float, nargs="+", default=[0.5, 1.0, 2.0], help="per-axis noise, mm")
    p.add_argument("--frames", type=int, default=20, help="frames of our own sequences")
    p.add_argument("--out", default="reports/latest")
    args = p.parse_args()
    limit_threads(1)
    entry = load_entry(Path(args.store) / args.model)
    model = entry.network if args.method == "network" else entry.fem
    base = NETWORK if args.method == "network" else dataclasses.replace(FEM, time_budget_ms=FEM_BUDGET_MS)
    paper = liver_paper_case()
    cases = [paper, *own_sequences(paper, entry.region, entry.fem.material, args.frames)]
    rows = []
    for case in cases:
        for mm in args.noise:
            sigma = mm * 1e-3
            clouds = noisy(case, noise=sigma)
            for setting, config in (
                ("default alpha", base),
                ("noise given", dataclasses.replace(base, noise=sigma)),
                ("noise x2 given", dataclasses.replace(base, noise=2 * sigma)),
            ):
                row = {"sequence": case.name, "noise_mm": mm, "setting": setting, **stream(model, clouds, config)}
                rows.append(row)
                print(
                    "{sequence:<28} {noise_mm:4.1f} mm  {setting:<15} TRE {tre_mm:.3f} mm  "
                    "force {force_error_pct:5.1f} %  {ms:6.1f} ms  alpha {alpha:.1e}".format(**row),
                    flush=True,
                )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "noise.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    print(f"wrote {out / 'noise.csv'}")


if __name__ == "__main__":
    main()

"""Levenberg-Marquardt against L-BFGS-B on the beam's cold starts, clean and degraded.

The beam benchmark's cases (FEM deformations from known tip loads, whole-surface clouds),
registered from rest by each optimizer under noise and outliers (service.synthetic.perturb, as
the stability suite makes them; the outliers with the robust losses), a cloud
far away, few points and a stiffer session. Prints one row per (condition, optimizer): median
ms, mean TRE, whether every field stayed finite, the statuses, mean evaluations.

    python benchmarks/beam_optimizers.py [--store model_store] [--cases 30]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from service.bench.beam import CONFIG, LBFGSB, beam_cases
from service.config import limit_threads
from service.registration.session import Session
from service.store import load_entry
from service.synthetic import perturb


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", default=str(Path(__file__).resolve().parents[1] / "model_store"))
    ap.add_argument("--cases", type=int, default=30)
    args = ap.parse_args()
    limit_threads(1)
    entry = load_entry(Path(args.store) / "beam")
    cases = beam_cases(entry, args.cases, 500)
    rng = np.random.default_rng(5)

    def outliers(p):  # the stability suite's: uniform within 2 cm of the cloud's bounding box
        return perturb(p, rng, outliers=0.1, spread=0.02)

    conditions = [
        ("clean", lambda p: p, {}),
        ("noise 0.5 mm", lambda p: perturb(p, rng, noise=5e-4), {}),
        ("noise 1 mm", lambda p: perturb(p, rng, noise=1e-3), {}),
        ("10 % outliers, trimmed 0.1", outliers, {"loss": "trimmed", "loss_param": 0.1}),
        ("10 % outliers, huber 1 mm", outliers, {"loss": "huber", "loss_param": 1e-3}),
        ("cloud 1 km away", lambda p: p + 1e3, {}),
        ("50 points", lambda p: p[:50], {}),
        ("E x 10", lambda p: p, {"E": 10 * float(entry.network.material.E)}),
    ]
    print("| condition | optimizer | ms (median) | mean TRE (mm) | all finite | statuses | evaluations |")
    print("|---|---|---|---|---|---|---|")
    for name, transform, extra in conditions:
        for label, base in (("Levenberg-Marquardt", CONFIG), ("L-BFGS-B", LBFGSB)):
            session = Session(entry.network, dataclasses.replace(base, **extra))
            rows = []
            for c in cases:
                pts = transform(c["points"])
                t0 = time.perf_counter()
                r = session.frame(pts)
                ms = 1e3 * (time.perf_counter() - t0)
                u = r.outputs["displacement"]
                rows.append(
                    (ms, np.linalg.norm(u - c["u"], axis=1).mean(), np.isfinite(u).all(), r.status, r.evaluations)
                )
            statuses: dict[str, int] = {}
            for row in rows:
                statuses[row[3]] = statuses.get(row[3], 0) + 1
            print(f"| {name} | {label} | {np.median([r[0] for r in rows]):.1f} | "
                  f"{1e3 * np.mean([r[1] for r in rows]):.3g} | "
                  f"{all(r[2] for r in rows)} | {', '.join(f'{k} {v}' for k, v in statuses.items())} | "
                  f"{np.mean([r[4] for r in rows]):.1f} |", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()

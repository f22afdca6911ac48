"""Two checkouts' Levenberg-Marquardt frames on the calibration sites, alternated and paired.

Each round runs each checkout's own ``service`` in a fresh process (one BLAS thread, as the
server runs; the order alternates between rounds) over the calibration sites (CALIBRATION_SEED,
no report uses them), made once here and handed to both: the Newton method at its gtol and the
network at the any-site part's settings. Per site and run: each frame's steps, time and
objective (J at the answer: lower is nearer the optimum), the mean TRE and median force error.

    python benchmarks/lm_model_pairs.py OLD_CHECKOUT NEW_CHECKOUT --model STORE/liver_paper \\
        --rounds 2 --out reports/lm-model/pairs.json
"""

from __future__ import annotations

import functools
import pickle
import statistics
import tempfile
from pathlib import Path

import calibration
import paired

#: what each process runs inside its checkout: one method over every site, a row per site; written
#: out in full (not service.bench.cases.score), since an older checkout may lack what it calls
_ONE_RUN = """
import dataclasses, json, pickle, sys, time
from pathlib import Path
import numpy as np
sys.path.insert(0, ".")
from service.bench.anysite import FEM, NETWORK_LM
from service.config import limit_threads
from service.registration.session import Session
from service.store import load_entry
limit_threads(1)
entry, cases = load_entry(Path(sys.argv[1])), pickle.loads(Path(sys.argv[2]).read_bytes())
fem = sys.argv[3] == "fem"
model, base = (entry.fem, FEM) if fem else (entry.network, NETWORK_LM)
rows = []
for case in cases:
    config = dataclasses.replace(base, support=tuple(int(i) for i in case.support), outputs=("displacement", "forces"))
    s, frames = Session(model, config), []
    for k, cloud in enumerate(case.clouds):
        t = time.perf_counter()
        r = s.frame(cloud, frame_id=k)
        ms = 1e3 * (time.perf_counter() - t)
        u, f = r.outputs["displacement"], case.net_forces[k]
        frames.append({"ms": ms, "steps": r.iterations, "objective": r.objective, "status": r.status,
                       "tre": float(np.linalg.norm(case.mesh.nodes + u - case.positions[k], axis=1).mean() * 1e3),
                       "force": float(100 * np.linalg.norm(r.net_force - f) / np.linalg.norm(f))})
    rows.append({"case": case.name, "frames": frames})
print(json.dumps(rows))
"""


def run(checkout: Path, model: Path, cases: Path, method: str) -> list[dict]:
    return paired.run_json(checkout, _ONE_RUN, model, cases, method)


def _summary_of_run(checkout: Path, model: Path, cases: Path, method: str) -> dict:
    return summary(run(checkout, Path(model), cases, method))


def _steps_and_median(s: dict) -> dict:
    return {c: (v["steps"], round(v["warm_median_ms"], 1)) for c, v in s.items()}


def summary(rows: list[dict]) -> dict:
    """Per site: steps, warm median and total ms, mean TRE, median force error, summed objective."""
    out = {}
    for row in rows:
        f = row["frames"]
        out[row["case"]] = {
            "steps": [x["steps"] for x in f],
            "warm_median_ms": statistics.median(x["ms"] for x in f[1:]),
            "warm_total_ms": sum(x["ms"] for x in f[1:]),
            "tre_mean_mm": statistics.mean(x["tre"] for x in f),
            "force_median_pct": statistics.median(x["force"] for x in f),
            "objective_sum": sum(x["objective"] for x in f),
        }
    return out


def main() -> int:
    p = paired.parser(__doc__)
    p.add_argument("--model", type=Path, required=True)
    p.add_argument("--sites", type=int, default=4)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--methods", nargs="+", default=["fem", "network"])
    args = p.parse_args()
    _, cases = calibration.cases(args)
    runs: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "cases.pkl"  # written here, read only by the runs below
        path.write_bytes(pickle.dumps(cases))
        for method in args.methods:
            runs[method] = paired.alternate(functools.partial(_summary_of_run, model=args.model, cases=path,
                                                              method=method),
                                            args, args.rounds, show=_steps_and_median)  # fmt: skip
    result = {}  # times over the rounds; the answers, the same every round (one thread), from the first
    for method, sides in runs.items():
        result[method] = {
            side: {
                case: {
                    "steps": sum(sides[side][0][case]["steps"]),
                    "warm_total_ms_median": statistics.median(r[case]["warm_total_ms"] for r in sides[side]),
                    "warm_median_ms_median": statistics.median(r[case]["warm_median_ms"] for r in sides[side]),
                    "tre_mean_mm": sides[side][0][case]["tre_mean_mm"],
                    "force_median_pct": sides[side][0][case]["force_median_pct"],
                    "objective_sum": sides[side][0][case]["objective_sum"],
                }
                for case in sides[side][0]
            }
            for side in sides
        }
    paired.write(args, runs, result, model=Path(args.model).name)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

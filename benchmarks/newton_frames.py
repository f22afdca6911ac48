"""The Newton method's warm frames on the paper's recorded sequence, in two checkouts,
alternated: a paired comparison of its Levenberg-Marquardt frame time (and the same answers).

    python benchmarks/newton_frames.py OLD_CHECKOUT NEW_CHECKOUT --model STORE/liver_paper \\
        --rounds 3 --frames 8 --out reports/newton-frames/pairs.json

Each round runs each checkout's own ``service`` in a fresh process (one BLAS thread, as the
server runs), the first `frames` frames of the sequence, gtol 1e-4."""

from __future__ import annotations

import statistics
from pathlib import Path

import paired

#: what each process runs inside its checkout: the frames' times, iterations and forces
_ONE_RUN = """
import dataclasses, json, sys, time
from pathlib import Path
sys.path.insert(0, ".")
from service.bench.cases import liver_paper_case
from service.bench.liver import FEM
from service.config import limit_threads
from service.registration.session import Session
from service.store import load_entry
limit_threads(1)
entry, case = load_entry(Path(sys.argv[1])), liver_paper_case()
config = dataclasses.replace(FEM, optimizer="levenberg-marquardt", gtol=1e-4,
                             support=tuple(int(i) for i in case.support), outputs=("forces",))
s, rows = Session(entry.fem, config), []
for cloud in case.clouds[: int(sys.argv[2])]:
    t = time.perf_counter()
    r = s.frame(cloud)
    rows.append({"ms": 1e3 * (time.perf_counter() - t), "iterations": r.iterations,
                 "net_force": [float(v) for v in r.net_force]})
print(json.dumps(rows))
"""


def run(checkout: Path, model: Path, frames: int) -> list[dict]:
    return paired.run_json(checkout, _ONE_RUN, model, frames)


def main() -> None:
    p = paired.parser(__doc__)
    p.add_argument("--model", type=Path, required=True)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--frames", type=int, default=8)
    args = p.parse_args()
    runs = paired.alternate(
        lambda checkout: run(checkout, args.model, args.frames), args, args.rounds,
        show=lambda frames: f"warm median {statistics.median(f['ms'] for f in frames[1:]):.1f} ms",
    )  # fmt: skip
    medians = {s: [statistics.median(f["ms"] for f in r[1:]) for r in runs[s]] for s in runs}
    summary = {
        "warm_median_ms": medians,
        "ratio_new_old": [n / o for o, n in zip(medians["old"], medians["new"], strict=True)],
        "iterations": {s: [f["iterations"] for f in runs[s][0]] for s in runs},
        "largest_net_force_difference_n": max(
            abs(a - b)
            for o, n in zip(runs["old"][0], runs["new"][0], strict=True)
            for a, b in zip(o["net_force"], n["net_force"], strict=True)
        ),  # fmt: skip
    }
    paired.write(args, runs, summary, frames=args.frames)


if __name__ == "__main__":
    main()

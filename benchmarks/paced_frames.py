"""The any-site part's network frames (Levenberg-Marquardt, the README's any-site row) back to
back, as `elastreg bench anysite` times them, and paced as a 30 Hz camera delivers them.

    python benchmarks/paced_frames.py --model STORE/liver_paper [--rounds 5] [--out FILE]

The sites are the bench's own (SITE_SEED, truth from the mesh subdivided once): this measures
what the reported frames cost at a camera's pace, it chooses nothing. Rounds alternate which
pacing goes first; each site's figure is the median of its warm frames' ``timing_ms.total``
over every round. One BLAS thread, as the server runs.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.bench.anysite import NETWORK_LM, anysite_cases
from service.bench.machine import describe
from service.config import limit_threads
from service.registration.session import Session
from service.store import load_entry

PERIOD = 1 / 30  # s between a 30 Hz camera's frames
MODES = ("back to back", "paced 30 Hz")


def run(entry, cases, mode: str, out: dict[str, list[float]]) -> None:
    """Every case's frames in one session each; warm frames' totals (ms) into `out` by case."""
    for case in cases:
        config = dataclasses.replace(NETWORK_LM, support=tuple(int(i) for i in case.support))
        session = Session(entry.model("network"), config)
        for k, cloud in enumerate(case.clouds):
            t0 = time.perf_counter()
            r = session.frame(cloud, frame_id=k)
            if k:
                out[case.name].append(r.timing_ms["total"])
            if mode != "back to back":
                time.sleep(max(0.0, PERIOD - (time.perf_counter() - t0)))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", required=True, help="a whole-surface liver entry (the any-site part's)")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--out", default=None, help="write the figures here (JSON)")
    args = p.parse_args()
    limit_threads(1)
    entry = load_entry(Path(args.model))
    cases = anysite_cases(entry, sites=6, frames=8)
    times: dict[str, dict[str, list[float]]] = {m: {c.name: [] for c in cases} for m in MODES}
    for rnd in range(args.rounds):
        for mode in MODES if rnd % 2 == 0 else MODES[::-1]:
            run(entry, cases, mode, times[mode])
    medians = {m: {k: float(np.median(v)) for k, v in d.items()} for m, d in times.items()}
    ratio = {k: medians[MODES[1]][k] / medians[MODES[0]][k] for k in medians[MODES[0]]}
    for m, d in medians.items():
        print(f"{m:13s} {' '.join(f'{v:5.1f}' for v in d.values())} ms (sites 1-{len(d)})")
    print(f"paced / back to back: {' '.join(f'{r:.2f}' for r in ratio.values())}")
    if args.out:
        report = {"machine": describe(), "rounds": args.rounds, "period_s": PERIOD, "ms_median": medians}
        Path(args.out).write_text(json.dumps({**report, "paced_over_back_to_back": ratio}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Where a warm any-site frame's time goes, on calibration sites only.

Registers the anysite generator's tool sites drawn from CALIBRATION_SEED (no report uses it)
with the network under the anysite part's Levenberg-Marquardt settings, one session per site,
twice; prints the median of each part of the frame's own timing (`timing_ms`) over the second
pass's warm frames, and with --profile the functions that took the time.

    python benchmarks/frame_anatomy.py --model /path/to/store/liver_paper [--profile]
"""

from __future__ import annotations

import cProfile
import dataclasses
import pstats
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import calibration

from service.bench.anysite import NETWORK_LM
from service.bench.machine import describe
from service.registration.session import Session


def main() -> int:
    p = calibration.parser(__doc__)
    p.add_argument("--profile", action="store_true", help="also profile the second pass")
    args = p.parse_args()
    entry, cases = calibration.cases(args)
    rows: list[dict] = []
    prof = cProfile.Profile()
    for second in (False, True):
        for case in cases:
            rows += stream(entry.network, case, measure=second, prof=prof if args.profile else None)
    m = describe()
    print(m.get("cpu"), "-", m.get("commit"))
    for key in rows[0]:
        print(f"{key:12s} {np.median([row.get(key, 0.0) for row in rows]):8.2f}")
    if args.profile:
        pstats.Stats(prof).sort_stats("tottime").print_stats(25)
    return 0


def stream(model, case, measure: bool, prof: cProfile.Profile | None) -> list[dict]:
    """One session through the case's frames; the warm frames' timings when `measure`."""
    support = tuple(int(i) for i in case.support)
    session = Session(model, dataclasses.replace(NETWORK_LM, support=support, outputs=("displacement", "forces")))
    rows = []
    for k, cloud in enumerate(case.clouds):
        warm = measure and k > 0  # the first frame of a stream is a cold start
        if warm and prof is not None:
            prof.enable()
        t0 = time.perf_counter()
        r = session.frame(cloud, frame_id=k)
        wall = 1e3 * (time.perf_counter() - t0)
        if prof is not None:
            prof.disable()
        if warm:
            rows.append({**r.timing_ms, "wall": wall, "iterations": r.iterations, "evaluations": r.evaluations})
    return rows


if __name__ == "__main__":
    raise SystemExit(main())

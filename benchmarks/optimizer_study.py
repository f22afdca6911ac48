"""Which optimizer and tolerance for whole-surface models: chosen on calibration sites only.

The anysite part reports tool sites drawn from SITE_SEED; this draws its own from
CALIBRATION_SEED (no report uses it) with the same generator and finer-mesh truth, and registers
them with the network under L-BFGS-B and Levenberg-Marquardt at several relative gradient
tolerances. The rule, fixed before the run: the faster optimizer where its error matches, and
the loosest tolerance whose mean TRE stays within 2 % of the default tolerance's at every site.
Iterations and evaluations decide; times are printed too, with the load average, since they
move with what else the machine runs.

    python benchmarks/optimizer_study.py --model /path/to/store/liver_anysite
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import calibration

from service.bench.anysite import NETWORK
from service.bench.cases import run_case

VARIANTS: dict[str, dict[str, Any]] = {
    "lbfgsb, gtol 3e-4 (default)": {},
    "lbfgsb, gtol 1e-3": {"gtol": 1e-3},
    "levenberg-marquardt, gtol 3e-4": {"optimizer": "levenberg-marquardt"},
    "levenberg-marquardt, gtol 1e-3": {"optimizer": "levenberg-marquardt", "gtol": 1e-3},
    "levenberg-marquardt, gtol 3e-3": {"optimizer": "levenberg-marquardt", "gtol": 3e-3},
    "levenberg-marquardt, gtol 1e-2": {"optimizer": "levenberg-marquardt", "gtol": 1e-2},
}


def main() -> int:
    args = calibration.parser(__doc__, out="optimizer-study/optimizer_study.json").parse_args()
    entry, cases = calibration.cases(args)
    rows = []
    for name, change in VARIANTS.items():
        config = dataclasses.replace(NETWORK, **change)
        for case in cases:
            run_case(entry.network, case, config)  # warm: compiled kernels, caches
            recs = run_case(entry.network, case, config)
            row = calibration.row(name, case, recs)
            rows.append(row)
            figures = (
                f"TRE {row['tre_mean_mm']:.3f} mm, force {row['force_error_median_pct']:.1f} %, "
                f"evaluations {sum(row['evaluations'])}, {row['ms_median_warm']:.1f} ms (load {row['load']:.1f})"
            )
            print(f"{name:>32} {case.name:>28}: {figures}", flush=True)
    calibration.write(args, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

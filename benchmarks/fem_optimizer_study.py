"""Which optimizer the Newton method's frames take: chosen on calibration sites only.

The any-site part reports the Newton method with L-BFGS-B, and method "auto" corrects frames
with it. Since the FEM's Levenberg-Marquardt steps go through its Jacobian's products
(a few solves a step once it holds one Jacobian), this registers the calibration sites
(CALIBRATION_SEED, no report uses them) with the Newton method under both, at its default
tolerance. The rule, fixed before the run: Levenberg-Marquardt replaces L-BFGS-B where its mean
TRE is within 2 % of L-BFGS-B's (or lower) at every site and its median warm frame is faster at
most of them. Times carry the load average, since they move with what else the machine runs.
With --auto, method "auto" likewise: its corrections under L-BFGS-B (as the any-site part runs
it, over the L-BFGS-B network) against Levenberg-Marquardt's (over the any-site
Levenberg-Marquardt network), by the same rule.

    python benchmarks/fem_optimizer_study.py --model /path/to/store/liver_paper [--auto] --out ...
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import calibration

from service.bench.anysite import FEM, NETWORK, NETWORK_LM
from service.bench.cases import run_case

VARIANTS = {name: dataclasses.replace(FEM, optimizer=name) for name in ("lbfgsb", "levenberg-marquardt")}
#: method "auto" as the any-site part runs it (the network under L-BFGS-B, the FEM correcting
#: with it) against the same over the any-site Levenberg-Marquardt network, whose corrections
#: then take Levenberg-Marquardt too (with --auto)
AUTO = {"auto, lbfgsb": NETWORK, "auto, levenberg-marquardt": NETWORK_LM}


def main() -> int:
    p = calibration.parser(__doc__, out="fem-optimizer/fem_optimizer_study.json")
    p.add_argument("--auto", action="store_true", help="method auto's two variants instead of the FEM's")
    args = p.parse_args()
    entry, cases = calibration.cases(args)
    # auto's threshold as the any-site part sets it: twice the build's validation mean error
    max_error = 2e-3 * float(entry.manifest["training"]["validation"]["mean_mm"])
    rows = []
    for case in cases:
        variants = AUTO if args.auto else VARIANTS
        for name, config in variants.items():
            if args.auto:
                auto = dataclasses.replace(config, method="auto", max_error=max_error)
                recs = run_case(entry.network, case, auto, "auto", corrector=entry.fem)
            else:
                recs = run_case(entry.fem, case, config)
            row = calibration.row(name, case, recs)
            rows.append(row)
            print(
                f"{name:>20} {case.name:>28}: TRE {row['tre_mean_mm']:.4f} mm, force "
                f"{row['force_error_median_pct']:.1f} %, evaluations {sum(row['evaluations'])}, "
                f"{row['ms_median_warm']:.0f} ms, converged {row['converged']:.2f}, FEM {row['fem_share']:.2f} "
                f"(load {row['load']:.1f})",
                flush=True,
            )
    calibration.write(args, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""How honest error_estimate is on noisy clouds, with and without the noise declared.

The anysite generator's calibration sites (CALIBRATION_SEED: no report uses them), every cloud
with Gaussian noise of --noise metres per axis; each site registered by the network under
Levenberg-Marquardt (the anysite part's settings) and L-BFGS-B, once with the noise declared
to the session and once without. Prints and writes Spearman's rho of estimate against true mean
nodal error, the share of frames whose estimate is under half their error, the median ratio,
the median error and the median frame time.

    python benchmarks/noisy_estimate.py --model /path/to/store/liver_paper
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import calibration

from service.bench.anysite import NETWORK, NETWORK_LM
from service.bench.cases import noisy, run_case

OPTIMIZERS = {"levenberg-marquardt": NETWORK_LM, "lbfgsb": NETWORK}


def main() -> int:
    p = calibration.parser(__doc__, out="noisy-estimate/noisy_estimate.json")
    p.add_argument("--noise", type=float, default=5e-4, help="per-axis noise, m")
    args = p.parse_args()
    from scipy.stats import spearmanr

    entry, clean = calibration.cases(args)
    cases = [noisy(c, noise=args.noise, seed=11) for c in clean]
    rows = []
    for name, base in OPTIMIZERS.items():
        for declared in (False, True):
            config = dataclasses.replace(base, noise=args.noise if declared else None)
            recs = [r for case in cases for r in run_case(entry.network, case, config)]
            est = np.array([r.error_estimate_mm for r in recs])
            err = np.array([r.tre_mm for r in recs])
            row = {
                "optimizer": name,
                "noise_declared": declared,
                "frames": len(recs),
                "spearman": float(spearmanr(est, err)[0]),
                "under_half": float(np.mean(est < 0.5 * err)),
                "median_ratio": float(np.median(est / err)),
                "median_error_mm": float(np.median(err)),
                "ms_median": float(np.median([r.ms for r in recs if r.frame > 0])),
            }
            rows.append(row)
            print(json.dumps(row))
    calibration.write(args, rows, noise_m=args.noise)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

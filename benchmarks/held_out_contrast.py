"""Sites a build trained on beside the ones it held out: the same build's network against the
Newton method at the calibration draw's sites.

`elastreg bench anysite` on a build of liver_paper_held_out.toml scores the six reported sites,
whose supports no training load touched. This scores the calibration draw's sites
(CALIBRATION_SEED: spread off the reported supports, so mostly inside what that build trained
on; a row's `held_out` says how much of its support the build kept off all the same, as the
liver's recorded support, which the draw does not avoid) the same way: the network with the
any-site settings (Levenberg-Marquardt, gtol 3e-3) and the Newton method, each site's mean TRE
and median force error, and the network's TRE over the Newton method's on the same frames (the
mesh's own error is in both; their ratio is the network's share). One pass: errors, not times,
are the point.

    python benchmarks/held_out_contrast.py --model STORE/liver_paper_held_out --out ...
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import calibration

from service.bench.anysite import FEM, LM_LABEL, NETWORK_LM
from service.bench.cases import held_out, run_case


def main() -> int:
    args = calibration.parser(__doc__, out="held-out/trained_sites.json").parse_args()
    entry, cases = calibration.cases(args)
    kept_off = entry.manifest["training"]["load_distribution"].get("keep_off", [])
    rows = []
    for case in cases:
        pair = []
        for name, model, config in ((LM_LABEL, entry.network, NETWORK_LM), ("fem", entry.fem, FEM)):
            row = calibration.row(name, case, run_case(model, case, config))
            rows.append(row)
            pair.append(row["tre_mean_mm"])
            tre, force = row["tre_mean_mm"], row["force_error_median_pct"]
            print(f"{name:>30} {case.name:>28}: TRE {tre:.4f} mm, force {force:.1f} %")
        held = held_out(entry, case.support) or "trained"
        for row in rows[-2:]:
            row["held_out"] = held
        rows[-2]["network_over_newton"] = pair[0] / pair[1]
        print(f"{'network / Newton':>30} {case.name:>28}: {pair[0] / pair[1]:.3f} ({held})", flush=True)
    calibration.write(args, rows, kept_off_nodes=len(kept_off))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

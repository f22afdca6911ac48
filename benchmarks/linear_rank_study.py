"""How many singular directions of a session's linear block the physics layout keeps
(LINEAR_RANK): accuracy and time per frame, on tool sites from the calibration seed (3026),
which the any-site benchmark never uses. Truth: the FEM on the model's own mesh (this compares
the operator with itself, truncated or not, so the inverse crime does not flatter either side).

    python benchmarks/linear_rank_study.py STORE/ENTRY [--ranks 64 96 128 100000] [--sites 3]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import service.surrogate.physics as physics
from service.bench.anysite import CALIBRATION_SEED, NETWORK, site_patches, site_region
from service.bench.cases import Case, run_case, summarise
from service.bench.machine import describe
from service.store import load_entry
from service.synthetic import make_sequence


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("entry")
    p.add_argument("--ranks", type=int, nargs="+", default=[64, 96, 128, 100_000])
    p.add_argument("--sites", type=int, default=3)
    p.add_argument("--frames", type=int, default=6)
    p.add_argument("--out", default=None)
    args = p.parse_args()
    entry = load_entry(Path(args.entry))
    mesh = entry.mesh
    rng = np.random.default_rng(CALIBRATION_SEED)
    region = site_region(mesh, entry.region, CALIBRATION_SEED)  # off the reported sites' supports
    max_force = float(entry.manifest["training"]["load_distribution"]["max_force"])
    cases = []
    for i, (site, tool, support) in enumerate(site_patches(mesh, region, args.sites, rng)):
        peak = float(rng.uniform(0.4, 0.9)) * max_force
        seq = make_sequence(
            mesh,
            entry.fem.material,
            tool,
            n_frames=args.frames,
            peak_force=peak,
            n_points=800,
            seed=CALIBRATION_SEED + i,
        )
        cases.append(Case(f"site {int(site)}", mesh, support, None, seq.clouds, seq.positions, seq.net_forces))
    rows: list[dict] = []
    for _ in range(2):  # two passes: the second's times are the warm ones
        rows = []
        for rank in args.ranks:
            physics.LINEAR_RANK = rank
            for case in cases:
                s = summarise(run_case(entry.network, case, NETWORK))
                rows.append(
                    {
                        "rank": rank,
                        **{
                            key: s[key]
                            for key in ("case", "tre_mean_mm", "force_error_median_pct", "ms_median", "iterations_mean")
                        },
                    }
                )
    for r in rows:
        print(json.dumps(r))
    if args.out:
        Path(args.out).write_text(json.dumps({"machine": describe(), "entry": args.entry, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

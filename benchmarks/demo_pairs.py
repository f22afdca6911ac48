"""`elastreg demo` in two checkouts, alternating, each run's figures kept: a paired latency
comparison on a shared machine (the answers must agree; the times are compared run by run).

    python benchmarks/demo_pairs.py OLD_CHECKOUT NEW_CHECKOUT --pairs 4 --out reports/demo/pairs.json

Each checkout runs with its own ``service`` package and model store (``python -m service.cli
demo`` inside it) under this interpreter."""

from __future__ import annotations

import re
import statistics
import subprocess
import sys
from pathlib import Path

import paired

FIGURES = {
    "latency_ms": r"latency:\s+median ([\d.]+) ms",
    "solve_ms": r"server solve: median ([\d.]+) ms",
    "error_mm": r"registration error: median ([\d.]+) mm",
    "force_error_pct": r"net force error:\s+median ([\d.]+) %",
    "estimate_mm": r"error estimate:\s+median ([\d.]+) mm",
}


def run(checkout: Path) -> dict:
    """One demo in `checkout`: its figures, parsed from what it prints."""
    out = subprocess.run([sys.executable, "-m", "service.cli", "demo"], cwd=checkout, capture_output=True,
                         text=True, check=True).stdout  # fmt: skip
    return {k: float(m.group(1)) if (m := re.search(p, out)) else None for k, p in FIGURES.items()}


def main() -> None:
    p = paired.parser(__doc__)
    p.add_argument("--pairs", type=int, default=4)
    args = p.parse_args()
    runs = paired.alternate(run, args, args.pairs)
    ratios = [n["latency_ms"] / o["latency_ms"] for o, n in zip(runs["old"], runs["new"], strict=True)]
    summary = {
        "latency_median_ms": {s: statistics.median(r["latency_ms"] for r in runs[s]) for s in runs},
        "latency_ratio_new_old": {"median": statistics.median(ratios), "each": ratios},
        "same_answers": all(_answers(o) == _answers(n) for o, n in zip(runs["old"], runs["new"], strict=True)),
    }
    paired.write(args, runs, summary)


def _answers(figures: dict) -> dict:
    """A run's figures but its times: what both checkouts must agree on."""
    return {k: v for k, v in figures.items() if k not in ("latency_ms", "solve_ms")}


if __name__ == "__main__":
    main()

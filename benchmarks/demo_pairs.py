"""`elastreg demo` in two checkouts, alternating, each run's figures kept: a paired latency
comparison on a shared machine (the answers must agree; the times are compared run by run).

    python benchmarks/demo_pairs.py OLD_CHECKOUT NEW_CHECKOUT --pairs 4 --out reports/demo/pairs.json

Each checkout runs with its own ``service`` package and model store (``python -m service.cli
demo`` inside it) under this interpreter."""

from __future__ import annotations

import argparse
import json
import platform
import re
import statistics
import subprocess
import sys
from pathlib import Path

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


def commit(checkout: Path) -> str:
    return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=checkout, capture_output=True, text=True,
                          check=True).stdout.strip()  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("old", type=Path)
    p.add_argument("new", type=Path)
    p.add_argument("--pairs", type=int, default=4)
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    runs: dict[str, list[dict]] = {"old": [], "new": []}
    for i in range(args.pairs):
        for side in ("old", "new"):
            runs[side].append(run(getattr(args, side)))
            print(i, side, runs[side][-1], flush=True)
    ratios = [n["latency_ms"] / o["latency_ms"] for o, n in zip(runs["old"], runs["new"], strict=True)]
    summary = {
        "latency_median_ms": {s: statistics.median(r["latency_ms"] for r in runs[s]) for s in runs},
        "latency_ratio_new_old": {"median": statistics.median(ratios), "each": ratios},
        "same_answers": all(
            {k: v for k, v in o.items() if k not in ("latency_ms", "solve_ms")}
            == {k: v for k, v in n.items() if k not in ("latency_ms", "solve_ms")}
            for o, n in zip(runs["old"], runs["new"], strict=True)
        ),
    }
    print(json.dumps(summary, indent=1))
    record = {"commits": {"old": commit(args.old), "new": commit(args.new)}, "machine": platform.processor()
              or platform.machine(), "cpu": _cpu(), "runs": runs, "summary": summary}  # fmt: skip
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=1) + "\n")


def _cpu() -> str:
    """The CPU's model name, family and model (lscpu), where lscpu runs."""
    try:
        text = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    keep = ("Model name", "CPU family", "Model:", "CPU(s):")
    return "; ".join(" ".join(line.split()) for line in text.splitlines() if line.startswith(keep))


if __name__ == "__main__":
    main()

"""What the calibration-site studies share: their command line and their sequences.

Each study registers the anysite generator's tool sites drawn from CALIBRATION_SEED (no report
uses it) on a whole-surface store entry, with one BLAS thread as the server runs::

    args = calibration.parser(__doc__, out="optimizer-study/optimizer_study.json").parse_args()
    entry, cases = calibration.cases(args)
    rows = [calibration.row(variant, case, run_case(...)) for ...]
    calibration.write(args, rows)
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.bench.anysite import CALIBRATION_SEED, anysite_cases
from service.bench.cases import Case
from service.bench.machine import describe
from service.config import limit_threads
from service.store import Entry, load_entry


def parser(
    doc: str, *, out: str | None = None, model_help: str = "a whole-surface store entry"
) -> argparse.ArgumentParser:
    """--model, --sites (4) and, given `out` (a path under reports/), --out; the description is
    the first line of the study's `doc`."""
    p = argparse.ArgumentParser(description=doc.splitlines()[0])
    p.add_argument("--model", required=True, help=model_help)
    p.add_argument("--sites", type=int, default=4)
    p.add_argument("--seed", type=int, default=CALIBRATION_SEED, help="the sites' draw (default: the calibration draw)")
    if out is not None:
        p.add_argument("--out", default=str(ROOT / "reports" / out))
    return p


def cases(args: argparse.Namespace) -> tuple[Entry, list[Case]]:
    """One BLAS thread; the entry at --model and its --sites sequences of 8 frames from the --seed
    draw (the calibration sites unless told)."""
    limit_threads(1)
    entry = load_entry(Path(args.model))
    return entry, anysite_cases(entry, sites=args.sites, frames=8, seed=getattr(args, "seed", CALIBRATION_SEED))


def row(variant: str, case: Case, recs: list) -> dict:
    """One variant's figures at one site: mean TRE, median force error, iterations and
    evaluations by frame, each frame's time and the warm frames' median, the converged share,
    the share the FEM answered (method auto), and the load average beside the times."""
    return {
        "variant": variant,
        "case": case.name,
        "tre_mean_mm": float(np.mean([r.tre_mm for r in recs])),
        "force_error_median_pct": float(np.median([r.force_error_pct for r in recs])),
        "iterations": [r.iterations for r in recs],
        "evaluations": [r.evaluations for r in recs],
        "ms": [r.ms for r in recs],
        "ms_median_warm": float(np.median([r.ms for r in recs[1:]])),
        "converged": float(np.mean([r.converged for r in recs])),
        "fem_share": float(np.mean([r.method_used == "fem" for r in recs])),
        "load": os.getloadavg()[0],
    }


def write(args: argparse.Namespace, rows: list[dict], **settings) -> None:
    """The study's rows to --out, with the machine's stamp, the model's name and any settings
    of the study's own (noise_m=..., say)."""
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(
        json.dumps({"machine": describe(), "model": Path(args.model).name, **settings, "rows": rows}, indent=1)
    )

"""What the calibration-site studies share: their command line and their sequences.

Each study registers the anysite generator's tool sites drawn from CALIBRATION_SEED (no report
uses it) on a whole-surface store entry, with one BLAS thread as the server runs::

    args = calibration.parser(__doc__, out="optimizer-study/optimizer_study.json").parse_args()
    entry, cases = calibration.cases(args)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.bench.anysite import CALIBRATION_SEED, anysite_cases
from service.bench.cases import Case
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
    if out is not None:
        p.add_argument("--out", default=str(ROOT / "reports" / out))
    return p


def cases(args: argparse.Namespace) -> tuple[Entry, list[Case]]:
    """One BLAS thread; the entry at --model and its --sites calibration sequences of 8 frames."""
    limit_threads(1)
    entry = load_entry(Path(args.model))
    return entry, anysite_cases(entry, sites=args.sites, frames=8, seed=CALIBRATION_SEED)

"""The command line of ``elastreg bench``: its flags, and the refusal of a command that cannot run
as asked (one line, exit status 2, before anything is written)."""

from __future__ import annotations

import argparse
import sys
from typing import NoReturn

from ..argtypes import build_minutes, model_id, whole_number
from .results import PARTS
from .truth import TRUTHS

#: what a bare ``elastreg bench`` runs: the build-minutes curve is hours of builds
DEFAULT_PARTS = PARTS[:-1]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "parts",
        nargs="*",
        type=part_name,
        default=list(DEFAULT_PARTS),
        help=f"parts to run (default: {', '.join(DEFAULT_PARTS)}; 'minutes' only when named)",
    )
    p.add_argument(
        "--store",
        default=None,
        help="model store holding the parts' models (default: $ELASTREG_STORE or the project's model_store/)",
    )
    p.add_argument(
        "--liver-model",
        type=model_id,
        default="liver_paper",
        help="the liver, pareto and stability parts' model (default: liver_paper); the pareto part also scores "
        "every model of the store named after it and '_'",
    )
    p.add_argument("--beam-model", type=model_id, default="beam", help="the beam part's model (default: beam)")
    p.add_argument(
        "--anysite-model",
        type=model_id,
        default="phantom",
        help="a whole-surface model for the anysite part (default: phantom)",
    )
    p.add_argument("--sites", type=whole_number(1), default=6, help="anysite: tool sites (sequences; default: 6)")
    p.add_argument(
        "--truth",
        choices=TRUTHS,
        default="subdivided",
        help="anysite: the truth's discretisation, linear tets on the mesh subdivided once or ten-node tets on it "
        "(default: subdivided)",
    )
    p.add_argument(
        "--out",
        default="reports/latest",
        help="report folder, whose other parts a run keeps (default: reports/latest, the minutes part's too)",
    )
    p.add_argument(
        "--replace",
        action="store_true",
        help="replace the report in --out whole instead of keeping the parts this run does not redo "
        "(a --smoke run needs it for a folder holding a report of full runs)",
    )
    p.add_argument("--quick", action="store_true", help="fewer frames and sweep points (minutes, not an hour)")
    p.add_argument(
        "--no-fem",
        action="store_true",
        help="skip the Newton-based method in the liver, stability and anysite parts (and anysite's auto, whose "
        "corrections it makes); the beam and pareto parts keep their short Newton rows",
    )
    g = p.add_argument_group("the minutes part (the build-minutes curve)")
    g.add_argument(
        "--build-minutes",
        type=build_minutes,
        nargs="*",
        default=[5.0, 10.0, 30.0, 60.0],
        metavar="M",
        help="budgets to build each scene at (default: 5 10 30 60); none: redraw the report from the rows kept",
    )
    g.add_argument(
        "--scenes",
        nargs="+",
        default=["benchmarks/scenes/liver_sofa.toml", "benchmarks/scenes/liver_deepphysx.toml"],
        help="scene files to build (default: the SOFA and DeepPhysX livers)",
    )
    g.add_argument(
        "--test-paths",
        type=whole_number(1),
        default=40,
        help="held-out test paths per scene (5 samples each; default: 40)",
    )
    g.add_argument(
        "--test-data", default=None, help="where the test sets are kept (default: ~/.cache/elastreg/test-data)"
    )
    g.add_argument(
        "--workers",
        type=whole_number(0),
        default=2,
        help="FEM worker processes of each build (0: in this process; default: 2)",
    )
    g.add_argument("--keep-store", default=None, help="keep each scene's last build in this store (default: discard)")
    g.add_argument(
        "--resume",
        default=None,
        metavar="PATH",
        help="merge the rows of a stopped run set aside beside --out (NAME.interrupted-TIME, or its "
        "minutes_rows.json), built on this machine at this commit, and skip the budgets they hold",
    )
    p.add_argument(
        "--smoke",
        type=model_id,
        metavar="MODEL",
        default=None,
        help="the parts (not minutes) on a tiny model of --store, in seconds, for the tests (into a report of "
        "full runs only with --replace)",
    )


def part_name(text: str) -> str:
    """A part's name, refused at parse time otherwise (before the report folder is made)."""
    if text not in PARTS:
        raise argparse.ArgumentTypeError(f"unknown part {text!r}; choose from {', '.join(PARTS)}")
    return text


def refuse(message: str) -> NoReturn:
    """A command that cannot run as asked: one line, exit status 2, nothing written."""
    print(f"error: {message}", file=sys.stderr)
    raise SystemExit(2)

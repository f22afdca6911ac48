"""What the paired-checkout studies share (demo_pairs.py, newton_frames.py, lm_model_pairs.py):
two checkouts on the command line, their runs alternated so that a shared machine's drift falls
on both, a snippet run inside each checkout, and the record stamped with the machine
(service.bench.machine) and each checkout's commit."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.bench.machine import describe

T = TypeVar("T")
SIDES = ("old", "new")


def parser(doc: str) -> argparse.ArgumentParser:
    """OLD and NEW checkouts and --out; the description is the first line of the study's `doc`."""
    p = argparse.ArgumentParser(description=doc.splitlines()[0])
    p.add_argument("old", type=Path)
    p.add_argument("new", type=Path)
    p.add_argument("--out", type=Path, required=True)
    return p


def alternate(
    run: Callable[[Path], T], args: argparse.Namespace, rounds: int, show: Callable[[T], object] = lambda r: r
) -> dict[str, list[T]]:
    """`run(checkout)` once per side, `rounds` times, old first in even rounds and new first in odd
    ones (a side always run first was measured to gain from it); each run's `show` printed as it
    ends. Runs are listed per side in round order, so index i of each side is one pair."""
    runs: dict[str, list[T]] = {side: [] for side in SIDES}
    for i in range(rounds):
        for side in order(i):
            runs[side].append(run(getattr(args, side)))
            print(i, side, show(runs[side][-1]), flush=True)
    return runs


def order(i: int) -> tuple[str, ...]:
    """The sides in the order round `i` runs them."""
    return SIDES if i % 2 == 0 else SIDES[::-1]


def run_json(checkout: Path, code: str, *argv: object):
    """`code` run by this Python in a fresh process inside `checkout` (its own ``service``), with
    `argv` as its arguments; the JSON its last line of output printed."""
    out = subprocess.run([sys.executable, "-c", code, *map(str, argv)], cwd=checkout, capture_output=True,
                         text=True, check=True).stdout  # fmt: skip
    return json.loads(out.strip().splitlines()[-1])


def write(args: argparse.Namespace, runs: dict, summary: dict, **extra) -> None:
    """The record at --out: each checkout's commit, the machine, `extra`, the runs, the summary."""
    print(json.dumps(summary, indent=1))
    commits = {side: _commit(getattr(args, side)) for side in SIDES}
    record = {"commits": commits, "machine": describe(), **extra, "runs": runs, "summary": summary}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=1) + "\n")


def _commit(checkout: Path) -> str:
    return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=checkout, capture_output=True, text=True,
                          check=True).stdout.strip()  # fmt: skip

"""``elastreg bench``: run the benchmark parts, then write the report (:mod:`.markdown`:
Markdown, CSV/JSON, PNG).

Parts: ``fem`` (Newton and sparse solvers on the liver), ``liver`` (the paper's liver experiment,
both methods), ``beam`` (the paper's beam experiment), ``pareto`` (error against run time),
``stability`` (stiff and extreme cases), ``anysite`` (tool sites spread over the load region,
loads held out, truth from a finer mesh, the error estimates' honesty), and, asked for by name since it takes hours,
``minutes`` (validation error against build minutes, :mod:`.minutes`). ``--smoke`` runs every
code path on a tiny model in seconds (the default tests do), so the report cannot rot; a smoke
report never mixes with full runs'.

Here the run as a whole: the flags are :mod:`.command`'s, the inputs checked before any work
:mod:`.inputs`', the parts run by :mod:`.parts`, the folder put in place by :mod:`.swap`.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import sys
from pathlib import Path

from .command import refuse
from .inputs import part_models, read_scenes, resumed_rows
from .markdown import write_report
from .parts import run_parts
from .results import MINUTES_ROWS, merge_previous, prior_part, prior_problem, prior_run
from .swap import Busy, carry_over, hold, keep_unplaced, put_in_place, recover, release, scratch_folder, set_aside


def main(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from ..config import Settings, default_store, limit_threads, setting_problems

    try:
        blas_threads = Settings().blas_threads
    except ValidationError as exc:  # an ELASTREG_* setting the server would refuse too
        refuse("the ELASTREG_* settings: " + "; ".join(setting_problems(exc)))
    if blas_threads:  # measure what the server runs: its solves use this many BLAS threads
        limit_threads(blas_threads)
    store = Path(args.store) if args.store else default_store()
    out = Path(os.path.abspath(args.out))  # "." and ".." named: the swap renames the folder by its name
    try:
        out = out.resolve() if out.is_symlink() else out  # the folder a link names is the one swapped
    except (RuntimeError, OSError) as exc:  # a loop of links
        refuse(f"--out {out} is a symbolic link that names no folder ({exc})")
    parts = list(dict.fromkeys(args.parts))
    if args.smoke is not None and "minutes" in parts:
        refuse("the minutes part builds scenes (--scenes), not a --smoke model")
    if args.resume is not None and "minutes" not in parts:
        refuse("--resume merges a stopped run's minutes rows: name the minutes part")
    if (out.exists() and not out.is_dir()) or not out.name:
        refuse(f"--out {out} is not a folder a report can replace")
    with contextlib.ExitStack() as held:
        taken = _hold(out, held)  # before `out` is read: a second run into it is refused, not merged over
        return _write(args, store, out, parts, blas_threads, held if not taken else None)


def _hold(out: Path, held: contextlib.ExitStack) -> bool:
    """Lock `out` for this run (released as `held` closes), refused where another run holds it;
    whether a lock file could be made (not before `out`'s parent exists)."""
    try:
        lock = hold(out)
    except Busy as exc:
        refuse(str(exc))
    held.callback(release, lock)
    return lock is not None


def _write(
    args: argparse.Namespace,
    store: Path,
    out: Path,
    parts: list[str],
    blas_threads: int | None,
    unheld: contextlib.ExitStack | None,
) -> int:
    """Clear what stopped runs left, run the parts and put the report in `out` (locked once made
    where it could not be before: `unheld`)."""
    try:  # what a run stopped while writing `out` left, cleared before `out` is read
        notes = recover(out)
    except Busy as exc:
        refuse(str(exc))
    except OSError as exc:
        refuse(f"cannot clear what a stopped run left beside {out}: {exc}")
    for note in notes:
        print(f"note: {note}", file=sys.stderr)
    prior = None if args.replace else prior_run(out)
    if args.smoke is not None and prior is not None and prior.get("smoke") is None:
        refuse(
            f"{out} holds a report of full runs, which a --smoke run's figures would mix with: give another --out, "
            "or --replace to replace it"
        )
    if prior is not None and (problem := prior_problem(out, parts, args.smoke)):
        refuse(f"{out / 'results.json'} is not a report this run can keep: {problem}; give another --out, or "
               "--replace to replace it")  # fmt: skip
    resumed = resumed_rows(Path(args.resume), None if args.replace else out) if args.resume is not None else []
    kept_rows = (prior_part(out, "minutes") or {}).get("rows") if prior is not None else None
    if "minutes" in parts and not args.build_minutes and not resumed and not kept_rows:
        refuse(f"--build-minutes with no values redraws the report from its rows, and {out} holds none (nor "
               "--resume): name the budgets to build")  # fmt: skip
    models, variants = part_models(args, store, parts)
    scenes = read_scenes(args) if "minutes" in parts else []
    try:  # only now: a refused command leaves nothing behind
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        refuse(f"cannot make the report folder {out}: {exc.strerror or exc}")
    if unheld is not None:
        _hold(out, unheld)
    # the whole new report is written beside `out`, then put in its place at once: a run that
    # stops at any instant (Ctrl-C, a crash, SIGKILL) leaves the old report or the new, not a mix
    try:
        new, lock, note = scratch_folder(out)
    except OSError as exc:
        refuse(f"cannot make a scratch folder for the report in or beside {out}: {exc.strerror or exc}")
    if note:
        print(f"note: {note}", file=sys.stderr)
    whole = args.replace or (prior is not None and prior.get("smoke") != args.smoke)
    finished = placed = False
    try:
        (new / "figures").mkdir()
        results = run_parts(args, parts, models, variants, scenes, out, new, blas_threads, resumed)
        results = merge_previous(results, None if args.replace else out)
        write_report(results, new)
        finished = True
        if not whole and new.parent != out:
            carry_over(out, new)
        try:
            note = put_in_place(new, out, whole)
        except OSError as exc:
            # the files not moved yet, under a name the next run does not clear
            aside = keep_unplaced(getattr(exc, "kept", new), out)
            print(f"error: could not put the report in {out} ({exc}); it is kept in {aside}", file=sys.stderr)
            return 1
        placed = True
    finally:
        kept = not placed and (finished or (new / MINUTES_ROWS).exists())
        if kept and not finished:  # a stopped minutes run: its hour-long builds' rows, set aside while locked
            with contextlib.suppress(OSError):  # else left in its scratch folder, which the next run sets aside
                new = set_aside(new, out)
            print(f"note: the minutes rows built so far are kept in {new / MINUTES_ROWS}", file=sys.stderr)
        os.close(lock)
        if not kept:
            shutil.rmtree(new, ignore_errors=True)  # a run stopped before its report went in
    if note:
        print(f"note: {note}", file=sys.stderr)
    print(f"report written to {out / 'report.md'} ({results['seconds']:.0f} s)")
    return 0

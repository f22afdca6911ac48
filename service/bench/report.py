"""``elastreg bench``: run the benchmark parts, then write the report (:mod:`.markdown`:
Markdown, CSV/JSON, PNG).

Parts: ``fem`` (Newton and sparse solvers on the liver), ``liver`` (the paper's liver experiment,
both methods), ``beam`` (the paper's beam experiment), ``pareto`` (error against run time),
``stability`` (stiff and extreme cases), ``anysite`` (tool sites the build never aimed at, truth
from a finer mesh, the error estimates' honesty), and, asked for by name since it takes hours,
``minutes`` (validation error against build minutes, :mod:`.minutes`). ``--smoke`` runs every code path on a tiny model in
seconds (the default tests do), so the report cannot rot; a smoke report never mixes with full runs'.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import logging
import os
import shutil
import sys
import time
from pathlib import Path
from typing import NoReturn

import numpy as np

from ..argtypes import build_minutes, model_id, whole_number
from .markdown import write_report
from .results import (
    MINUTES_ROWS,
    PARTS,
    merge_previous,
    prior_part,
    prior_run,
    read_minutes_rows,
    write_minutes_rows,
)
from .swap import Busy, carry_over, hold, keep_unplaced, put_in_place, recover, release, scratch_folder, set_aside
from .truth import TRUTHS

log = logging.getLogger(__name__)

#: what a bare ``elastreg bench`` runs: the build-minutes curve is hours of builds
DEFAULT_PARTS = PARTS[:-1]
LIVER_HINT = 'elastreg train benchmarks/scenes/liver_paper.toml (docs/usage.md, "The paper\'s liver")'
VARIANT_HINT = "elastreg train benchmarks/scenes/liver_paper.toml --name ID ... (docs/usage.md's recipe)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "parts",
        nargs="*",
        type=_part,
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


def _part(text: str) -> str:
    """A part's name, refused at parse time otherwise (before the report folder is made)."""
    if text not in PARTS:
        raise argparse.ArgumentTypeError(f"unknown part {text!r}; choose from {', '.join(PARTS)}")
    return text


def _refuse(message: str) -> NoReturn:
    """A command that cannot run as asked: one line, exit status 2, nothing written."""
    print(f"error: {message}", file=sys.stderr)
    raise SystemExit(2)


def _entry(store: Path, name: str, hint: str):
    from ..store import StoreError, load_entry

    try:
        return load_entry(store / name)
    except StoreError as exc:
        _refuse(f"model {name!r} is not usable in {store} ({exc}); build it with: {hint}")


def _smoke_case(entry):
    """A 3-frame synthetic case on a small model: a tool at the far end, a larger support."""
    from .cases import synthetic_case

    mesh, region = entry.mesh, entry.region
    tip = region[np.argmax(mesh.nodes[region, 0])]
    in_region = np.isin(mesh.surface_patch(tip, 40), region)
    patch = mesh.surface_patch(tip, 40)[in_region]
    max_force = float(entry.manifest["training"]["load_distribution"]["max_force"])
    return synthetic_case("smoke", mesh, entry.fem.material, patch[:4], patch[:10], frames=3,
                          peak_force=0.5 * max_force, n_points=150)  # fmt: skip


def main(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from ..config import Settings, default_store, limit_threads, setting_problems

    try:
        blas_threads = Settings().blas_threads
    except ValidationError as exc:  # an ELASTREG_* setting the server would refuse too
        _refuse("the ELASTREG_* settings: " + "; ".join(setting_problems(exc)))
    if blas_threads:  # measure what the server runs: its solves use this many BLAS threads
        limit_threads(blas_threads)
    store = Path(args.store) if args.store else default_store()
    out = Path(os.path.abspath(args.out))  # "." and ".." named: the swap renames the folder by its name
    try:
        out = out.resolve() if out.is_symlink() else out  # the folder a link names is the one swapped
    except (RuntimeError, OSError) as exc:  # a loop of links
        _refuse(f"--out {out} is a symbolic link that names no folder ({exc})")
    parts = list(dict.fromkeys(args.parts))
    if args.smoke is not None and "minutes" in parts:
        _refuse("the minutes part builds scenes (--scenes), not a --smoke model")
    if args.resume is not None and "minutes" not in parts:
        _refuse("--resume merges a stopped run's minutes rows: name the minutes part")
    if (out.exists() and not out.is_dir()) or not out.name:
        _refuse(f"--out {out} is not a folder a report can replace")
    with contextlib.ExitStack() as held:
        taken = _hold(out, held)  # before `out` is read: a second run into it is refused, not merged over
        return _write(args, store, out, parts, blas_threads, held if not taken else None)


def _hold(out: Path, held: contextlib.ExitStack) -> bool:
    """Lock `out` for this run (released as `held` closes), refused where another run holds it;
    whether a lock file could be made (not before `out`'s parent exists)."""
    try:
        lock = hold(out)
    except Busy as exc:
        _refuse(str(exc))
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
        _refuse(str(exc))
    except OSError as exc:
        _refuse(f"cannot clear what a stopped run left beside {out}: {exc}")
    for note in notes:
        print(f"note: {note}", file=sys.stderr)
    prior = None if args.replace else prior_run(out)
    if args.smoke is not None and prior is not None and prior.get("smoke") is None:
        _refuse(
            f"{out} holds a report of full runs, which a --smoke run's figures would mix with: give another --out, "
            "or --replace to replace it"
        )
    resumed = _resumed(Path(args.resume), None if args.replace else out) if args.resume is not None else []
    models, variants = _models(args, store, parts)
    scenes = _scenes(args) if "minutes" in parts else []
    try:  # only now: a refused command leaves nothing behind
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        _refuse(f"cannot make the report folder {out}: {exc.strerror or exc}")
    if unheld is not None:
        _hold(out, unheld)
    # the whole new report is written beside `out`, then put in its place at once: a run that
    # stops at any instant (Ctrl-C, a crash, SIGKILL) leaves the old report or the new, not a mix
    try:
        new, lock, note = scratch_folder(out)
    except OSError as exc:
        _refuse(f"cannot make a scratch folder for the report in or beside {out}: {exc.strerror or exc}")
    if note:
        print(f"note: {note}", file=sys.stderr)
    whole = args.replace or (prior is not None and prior.get("smoke") != args.smoke)
    finished = placed = False
    try:
        (new / "figures").mkdir()
        results = _run_parts(args, parts, models, variants, scenes, out, new, blas_threads, resumed)
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


def _models(args: argparse.Namespace, store: Path, parts: list[str]) -> tuple[dict, dict]:
    """The model each part runs on ({part: entry}; the fem and minutes parts take none) and the
    pareto part's variants of the liver model ({id: entry}), each checked for what its part
    needs before any work: a model that lacks it is one line and exit status 2, not a traceback
    (or a variant silently left out) minutes into the run."""
    from .beam import beam_missing
    from .cases import liver_data_missing, not_on_paper_liver

    def on_liver(entry) -> str | None:
        return not_on_paper_liver(entry.mesh, entry.region)

    if args.smoke is not None:  # every part on the one model, its own cases: the liver's needs none
        names = dict.fromkeys(parts, args.smoke)
        needs = {"beam": beam_missing}
        hints = {args.smoke: "elastreg train SCENE"}
        variants = []
    else:
        if "fem" in parts and (missing := liver_data_missing()):
            _refuse(f"the fem part cannot run: {missing}")
        named = {"liver": args.liver_model, "pareto": args.liver_model, "stability": args.liver_model,
                 "beam": args.beam_model, "anysite": args.anysite_model}  # fmt: skip
        names = {part: named[part] for part in parts if part in named}
        needs = {"liver": on_liver, "pareto": on_liver, "stability": on_liver, "beam": beam_missing}
        hints = {args.liver_model: LIVER_HINT, args.beam_model: "elastreg train beam"}
        variants = _variant_ids(store, args.liver_model) if "pareto" in parts else []
        hints |= dict.fromkeys(variants, f"{VARIANT_HINT}, or remove the folder from the store")
    loaded = {
        name: _entry(store, name, hints.get(name, f"elastreg train {name}"))
        for name in dict.fromkeys([*names.values(), *variants])
    }
    for name in variants:  # a copy under another name (a backup) is no variant: open_store refuses it too
        if loaded[name].id != name:
            _refuse(f"model {name!r}, a variant the pareto part scores, says it is {loaded[name].id!r} (rename or "
                    "remove the folder)")  # fmt: skip
    for part, name in [*names.items(), *(("pareto", v) for v in variants)]:
        if part in needs and (missing := needs[part](loaded[name])):
            _refuse(f"model {name!r} cannot run the {part} part: {missing}")
    return {part: loaded[name] for part, name in names.items()}, {name: loaded[name] for name in variants}


def _resumed(path: Path, out: Path | None) -> list[dict]:
    """The rows of the stopped run set aside at `path` that the report in `out` lacks, each checked
    to be built on this machine at this commit (a curve compares builds of one machine and code;
    refused, one line, otherwise)."""
    from . import machine

    try:
        rows = read_minutes_rows(path)
    except ValueError as exc:
        _refuse(f"--resume: {exc}")
    report = (prior_part(out, "minutes") or {}).get("rows", []) if out is not None else []
    here = machine.describe()
    new = [r for r in rows if r not in report]
    for r in new:
        if (r["commit"], r["cpu"]) != (here["commit"], here["cpu"]):
            _refuse(f"--resume {path}: its row for {r['scene']} at {r['minutes']:g} minutes was built at commit "
                    f"{r['commit']} on {r['cpu']}, this run is commit {here['commit']} on {here['cpu']} "
                    "(rebuild those budgets here instead)")  # fmt: skip
    return new


def _variant_ids(store: Path, liver_model: str) -> list[str]:
    """The pareto part's variants: every folder of the store named after the liver model and '_'
    (docs/usage.md's recipe: liver_paper_small, ...)."""
    try:
        return sorted(p.name for p in store.iterdir() if p.name.startswith(liver_model + "_") and p.is_dir())
    except OSError:  # no store: the liver model's own check says so
        return []


def _scenes(args: argparse.Namespace) -> list:
    """The minutes part's scenes, read before any work (none to redraw the report from its rows)."""
    from ..scene import SceneError, load_scene

    try:
        return [load_scene(s) for s in args.scenes] if args.build_minutes else []
    except SceneError as exc:
        why = "; ".join(str(exc).splitlines())  # a scene's every fault, one line
        _refuse(f"{why} (the default scenes are relative to the repository's root)")


def _run_parts(
    args: argparse.Namespace,
    parts: list[str],
    models: dict,
    variants: dict,
    scenes: list,
    out: Path,
    new: Path,
    blas_threads: int | None,
    resumed: list[dict],
) -> dict:
    """Every part in `parts` on its model in `models` (the pareto part's `variants` beside its
    own), each figure drawn into the scratch folder `new`'s figures/ (the minutes part's rows
    written there after each build); the results, before the merge with the report in `out`
    (whose minutes rows the minutes part extends)."""
    from .. import spare
    from . import machine

    results: dict = {
        "machine": {**machine.describe(), "blas_threads": blas_threads, "spare_threads": spare.threads()},
        "started": time.strftime("%Y-%m-%d %H:%M:%S"),
        "smoke": args.smoke,  # the tiny model of a --smoke run: its report merges with no full run's
        "parts": {},
    }
    quick = args.quick or args.smoke is not None
    fem_on = not args.no_fem
    figures = new / "figures"
    t_all = time.perf_counter()

    if args.smoke is not None:  # one model for every part
        entry = next(iter(models.values()))
        base = _smoke_case(entry)

    if "fem" in parts:
        from .cases import liver_paper_case
        from .fem import newton_benchmark

        if args.smoke is not None:
            case, tool, material = base, base.support[:4], entry.fem.material
        else:  # the FEM needs no trained model: the paper's material on its liver
            case, material = liver_paper_case(), _paper_material()
            tool = np.loadtxt(case_tool_file(), dtype=np.int64)
        results["parts"]["fem"] = newton_benchmark(case, material, tool, repeats=1 if quick else 3)

    if "liver" in parts:
        from . import liver as lv
        from .cases import rest_baseline, run_case, summarise
        from .liver import FEM, FEM_LM, FEM_LM_LABEL, LM_LABEL, NETWORK, NETWORK_LM, liver_part

        if args.smoke is not None:
            recs = (rest_baseline(base) + run_case(entry.network, base, NETWORK) + run_case(entry.network, base, NETWORK_LM, LM_LABEL)
                    + run_case(entry.network, base, lv.WHOLE_SURFACE_LM, lv.WHOLE_LM_LABEL)
                    + run_case(entry.fem, base, FEM) + run_case(entry.fem, base, FEM_LM, FEM_LM_LABEL))  # fmt: skip
            methods = ("none (rest shape)", "network", LM_LABEL, lv.WHOLE_LM_LABEL, "fem", FEM_LM_LABEL)
            summaries = [summarise([r for r in recs if r.method == m]) for m in methods]
            results["parts"]["liver"] = {"records": recs, "summaries": summaries}
        else:
            results["parts"]["liver"] = liver_part(models["liver"], frames=15 if quick else None,
                                                   own_frames=6 if quick else 20, fem=fem_on, passes=1 if quick else 3)  # fmt: skip

    if "beam" in parts:
        from .beam import beam_part
        from .pareto import plot

        n = 4 if args.smoke is not None else (15 if quick else 60)
        sweep = (dict(gtols=(1e-2,), caps=(5,), points=(50,), fem_gtols=(1e-2,), fem_cases=1, lbfgsb_gtols=(1e-2,),
                      fem_lm_gtols=(1e-2,))
                 if args.smoke is not None else None)  # fmt: skip
        results["parts"]["beam"] = beam_part(
            models["beam"], n_cases=n, n_points=150 if args.smoke else 500, sweep=sweep
        )
        plot(results["parts"]["beam"]["pareto"], figures / "beam_pareto.png", "error against run time: the beam")

    if "pareto" in parts:
        from .cases import liver_paper_case
        from .pareto import pareto_part, plot

        case = base if args.smoke is not None else _first(liver_paper_case(), 12 if quick else 50)
        surrogates = {}
        if args.smoke is None:
            named = {args.liver_model: models["pareto"], **variants}
            surrogates = {_surrogate_label(k, e.manifest["network"]): e.network for k, e in named.items()}
        if args.smoke is not None:
            sweep = dict(
                gtols=(1e-2, 1e-4),
                caps=(5,),
                points=(50,),
                fem_gtols=(1e-2,),
                fem_frames=2,
                alphas=(1e-6,),
                lm_gtols=(1e-3,),
                fem_lm_gtols=(1e-2,),
                passes=2,
            )
        elif quick:
            sweep = dict(
                gtols=(1e-2, 1e-3, 1e-4, 1e-5),
                caps=(5, 20),
                points=(100, 500),
                fem_gtols=(1e-3, 1e-4),
                fem_frames=4,
                alphas=(3e-8,),
                lm_gtols=(1e-3, 1e-4),
                fem_lm_gtols=(1e-3, 1e-4),
                passes=1,
            )
        else:
            sweep = {}
        rows = pareto_part(models["pareto"], case, variants=surrogates, **sweep)
        results["parts"]["pareto"] = rows
        plot(rows, figures / "pareto.png", f"error against run time: {case.name}")

    if "stability" in parts:
        from .cases import liver_paper_case
        from .stability import stability_part

        if args.smoke is not None:
            results["parts"]["stability"] = stability_part(entry, base, frames=1, fem=fem_on, tool_size=4,
                                                           peak_force=0.3 * float(entry.manifest["training"]["load_distribution"]["max_force"]),
                                                           far=0.25 * entry.mesh.size)  # fmt: skip
        else:
            results["parts"]["stability"] = stability_part(
                models["stability"], liver_paper_case(), frames=6 if quick else 12, fem=fem_on
            )

    if "minutes" in parts:
        from .minutes import latest, merge, minutes_part
        from .minutes import plot as plot_minutes

        prior = None if args.replace else prior_part(out, "minutes")
        test_data = Path(args.test_data) if args.test_data else Path.home() / ".cache" / "elastreg" / "test-data"

        previous = (prior or {}).get("rows", [])  # none with --replace
        for row in resumed:  # a stopped run's rows, as if it had finished
            previous = merge(previous, row)
        results["parts"]["minutes"] = minutes_part(
            scenes,
            args.build_minutes,
            previous=previous,
            built=frozenset((r["scene"], r["minutes"]) for r in resumed if r.get("layout") == "physics"),
            test_paths=args.test_paths,
            test_data=test_data,
            workers=args.workers,
            keep=Path(args.keep_store) if args.keep_store else None,
            on_row=functools.partial(write_minutes_rows, new),  # never the live `out`: no mix
        )
        plot_minutes(latest(results["parts"]["minutes"]["rows"]), figures / "build_minutes.png")

    if "anysite" in parts:
        from .anysite import anysite_part, plot_honesty

        if args.smoke is not None:
            results["parts"]["anysite"] = anysite_part(entry, sites=2, frames=2, fem=fem_on, passes=1, truth=args.truth)
        else:
            results["parts"]["anysite"] = anysite_part(
                models["anysite"],
                sites=args.sites,
                frames=4 if quick else 8,
                fem=fem_on,
                passes=1 if quick else 3,
                truth=args.truth,
            )
        results["parts"]["anysite"]["model"] = args.smoke or args.anysite_model
        plot_honesty(results["parts"]["anysite"]["records"], figures / "anysite_estimates.png")

    results["seconds"] = time.perf_counter() - t_all
    return results


def _surrogate_label(name: str, net: dict) -> str:
    """A variant's name and size, for the Pareto table: 'liver_paper_small (256x256, r 64, 0.2M)'."""
    size = "x".join(str(h) for h in net.get("hidden", []))
    rank = f", r {net['rank']}" if net.get("rank") else ""
    skip = ", physics skip" if net.get("physics_skip") else ""
    return f"{name} ({size}{rank}{skip}, {net.get('parameters', 0) / 1e6:.2f}M parameters)"


def case_tool_file() -> Path:
    from .cases import LIVER

    return LIVER / "sequences" / "neohookean" / "s1" / "tool-vertices-default.txt"


def _paper_material():
    from ..fem.material import NeoHookean

    return NeoHookean(4500.0, 0.49)  # the paper's liver: E = 4500 Pa, nu = 0.49


def _first(case, frames: int):
    return dataclasses.replace(
        case, clouds=case.clouds[:frames], positions=case.positions[:frames], net_forces=case.net_forces[:frames]
    )

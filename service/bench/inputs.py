"""What the parts run on, each checked before any work: each part's model, the minutes part's
scenes, and a stopped minutes run's rows to resume; one line and exit status 2 where one lacks
what its part needs, not a traceback minutes into the run."""

from __future__ import annotations

import argparse
from pathlib import Path

from .command import refuse
from .results import prior_part, read_minutes_rows

LIVER_HINT = 'elastreg train benchmarks/scenes/liver_paper.toml (docs/usage.md, "The paper\'s liver")'
VARIANT_HINT = "elastreg train benchmarks/scenes/liver_paper.toml --name ID ... (docs/usage.md's recipe)"


def _entry(store: Path, name: str, hint: str):
    from ..store import StoreError, load_entry

    try:
        return load_entry(store / name)
    except StoreError as exc:
        refuse(f"model {name!r} is not usable in {store} ({exc}); build it with: {hint}")


def part_models(args: argparse.Namespace, store: Path, parts: list[str]) -> tuple[dict, dict]:
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
            refuse(f"the fem part cannot run: {missing}")
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
            refuse(f"model {name!r}, a variant the pareto part scores, says it is {loaded[name].id!r} (rename or "
                    "remove the folder)")  # fmt: skip
    for part, name in [*names.items(), *(("pareto", v) for v in variants)]:
        if part in needs and (missing := needs[part](loaded[name])):
            refuse(f"model {name!r} cannot run the {part} part: {missing}")
    return {part: loaded[name] for part, name in names.items()}, {name: loaded[name] for name in variants}


def _variant_ids(store: Path, liver_model: str) -> list[str]:
    """The pareto part's variants: every folder of the store named after the liver model and '_'
    (docs/usage.md's recipe: liver_paper_small, ...)."""
    try:
        return sorted(p.name for p in store.iterdir() if p.name.startswith(liver_model + "_") and p.is_dir())
    except OSError:  # no store: the liver model's own check says so
        return []


def read_scenes(args: argparse.Namespace) -> list:
    """The minutes part's scenes, each read and checked whole (mesh, boundary, load region) before
    any work, every fault of every scene in one line (none to redraw the report from its rows):
    a scene that parses but whose mesh or clamp cannot be used failed an hour into the run."""
    from ..build import load_spec
    from ..scene import load_scene

    if not args.build_minutes:
        return []
    scenes, faults = [], []
    for path in args.scenes:
        try:
            scene = load_scene(path)
            mesh, loaded = scene.build_mesh()
            load_spec(scene, mesh, loaded)
        except ValueError as exc:  # a SceneError is one, each line a fault
            faults += str(exc).splitlines()
        else:
            scenes.append(scene)
    if faults:
        refuse(f"{'; '.join(faults)} (the default scenes are relative to the repository's root)")
    return scenes


def resumed_rows(path: Path, out: Path | None) -> list[dict]:
    """The rows of the stopped run set aside at `path` that the report in `out` lacks, each checked
    to be built on this machine at this commit (a curve compares builds of one machine and code;
    refused, one line, otherwise)."""
    from . import machine

    try:
        rows = read_minutes_rows(path)
    except ValueError as exc:
        refuse(f"--resume: {exc}")
    report = (prior_part(out, "minutes") or {}).get("rows", []) if out is not None else []
    here = machine.describe()
    new = [r for r in rows if r not in report]
    for r in new:
        if (r["commit"], r["cpu"]) != (here["commit"], here["cpu"]):
            refuse(f"--resume {path}: its row for {r['scene']} at {r['minutes']:g} minutes was built at commit "
                    f"{r['commit']} on {r['cpu']}, this run is commit {here['commit']} on {here['cpu']} "
                    "(rebuild those budgets here instead)")  # fmt: skip
    return new

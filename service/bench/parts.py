"""Running the parts: each part on its model (or, for ``--smoke``, every part on one tiny model
with its own cases), its figures drawn into the run's scratch folder; the results, before the
merge with the report already in ``--out``."""

from __future__ import annotations

import argparse
import dataclasses
import functools
import time
from pathlib import Path

import numpy as np

from .results import prior_part, write_minutes_rows


def smoke_case(entry):
    """A 3-frame synthetic case on a small model: a tool at the far end, a larger support."""
    from .cases import synthetic_case

    mesh, region = entry.mesh, entry.region
    tip = region[np.argmax(mesh.nodes[region, 0])]
    in_region = np.isin(mesh.surface_patch(tip, 40), region)
    patch = mesh.surface_patch(tip, 40)[in_region]
    max_force = float(entry.manifest["training"]["load_distribution"]["max_force"])
    return synthetic_case("smoke", mesh, entry.fem.material, patch[:4], patch[:10], frames=3,
                          peak_force=0.5 * max_force, n_points=150)  # fmt: skip


def run_parts(
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
        "quick": args.quick,  # fewer frames and sweep points: each part's stamp says so (merge_previous)
        "parts": {},
    }
    quick = args.quick or args.smoke is not None
    fem_on = not args.no_fem
    figures = new / "figures"
    t_all = time.perf_counter()

    if args.smoke is not None:  # one model for every part
        entry = next(iter(models.values()))
        base = smoke_case(entry)

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

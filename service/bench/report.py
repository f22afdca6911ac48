"""``elastreg bench``: run the benchmark parts and write the report (Markdown, CSV/JSON, PNG).

Parts: ``fem`` (Newton and sparse solvers on the liver), ``liver`` (the paper's liver experiment,
both methods), ``beam`` (the paper's beam experiment), ``pareto`` (error against run time),
``stability`` (stiff and extreme cases), ``anysite`` (tool sites the build never aimed at, truth
from a finer mesh, the error estimates' honesty), and, asked for by name since it takes hours,
``minutes`` (validation error against build minutes, :mod:`.minutes`). ``--smoke`` runs every code path on a tiny model in
seconds (the default tests do), so the report cannot rot.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import logging
import time
from pathlib import Path

import numpy as np

from ..optional import need
from .truth import TRUTHS

log = logging.getLogger(__name__)

PARTS = ("fem", "liver", "beam", "pareto", "stability", "anysite", "minutes")
#: what a bare ``elastreg bench`` runs: the build-minutes curve is hours of builds
DEFAULT_PARTS = PARTS[:-1]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "parts",
        nargs="*",
        default=list(DEFAULT_PARTS),
        help=f"parts to run (default: {', '.join(DEFAULT_PARTS)}; 'minutes' only when named)",
    )
    p.add_argument("--store", default=None, help="model store holding liver_paper and beam (default: the project's)")
    p.add_argument("--liver-model", default="liver_paper")
    p.add_argument("--beam-model", default="beam")
    p.add_argument(
        "--anysite-model", default="phantom", help="a whole-surface model for the anysite part (default: phantom)"
    )
    p.add_argument("--sites", type=int, default=6, help="anysite: tool sites (sequences)")
    p.add_argument(
        "--truth",
        choices=TRUTHS,
        default="subdivided",
        help="anysite: the truth's discretisation, linear tets on the mesh subdivided once or ten-node tets on it",
    )
    p.add_argument("--out", default="reports/latest", help="report folder (default: reports/latest)")
    p.add_argument("--quick", action="store_true", help="fewer frames and sweep points (minutes, not an hour)")
    p.add_argument(
        "--no-fem",
        action="store_true",
        help="skip the Newton-based method (and anysite's auto, whose corrections it makes) where it is slow",
    )
    g = p.add_argument_group("the minutes part (the build-minutes curve)")
    g.add_argument(
        "--build-minutes",
        type=float,
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
    g.add_argument("--test-paths", type=int, default=40, help="held-out test paths per scene (5 samples each)")
    g.add_argument(
        "--test-data", default=None, help="where the test sets are kept (default: ~/.cache/elastreg/test-data)"
    )
    g.add_argument("--workers", type=int, default=2, help="FEM worker processes of each build")
    g.add_argument("--keep-store", default=None, help="keep each scene's last build in this store (default: discard)")
    p.add_argument(
        "--smoke", metavar="MODEL", default=None, help="every part on a tiny model of --store (seconds; for the tests)"
    )


_TRUTH_TEXT = {
    "subdivided": "the Neo-Hookean solution on the mesh subdivided once",
    "quadratic": "the Neo-Hookean solution on ten-node tets of the mesh (a uniform traction over the tool "
    "patch's triangles)",
}


def _jsonable(x):
    if dataclasses.is_dataclass(x):
        return dataclasses.asdict(x)
    if isinstance(x, (np.integer, np.floating, np.bool_)):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(type(x).__name__)


def _write_csv(path: Path, rows: list[dict]) -> None:
    if not rows:
        return
    rows = [dataclasses.asdict(r) if dataclasses.is_dataclass(r) else r for r in rows]
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow(
                {k: json.dumps(v, default=_jsonable) if isinstance(v, (list, dict)) else v for k, v in r.items()}
            )


def _fmt(v, digits: int = 3) -> str:
    if isinstance(v, (list, tuple)):  # a cell of several figures (each pass's time, statuses)
        return ", ".join(_fmt(x, digits) for x in v)
    if isinstance(v, float):
        if not np.isfinite(v):
            return str(v)
        return f"{v:.{digits}g}" if abs(v) < 1e-2 or abs(v) >= 1e4 else f"{v:.{digits}f}".rstrip("0").rstrip(".")
    return str(v)


def _table(rows: list[dict], cols: list[tuple[str, str]]) -> str:
    head = "| " + " | ".join(label for _, label in cols) + " |\n|" + "---|" * len(cols) + "\n"
    return head + "".join("| " + " | ".join(_fmt(r.get(k, "")) for k, _ in cols) + " |\n" for r in rows)


def _entry(store: Path, model_id: str, hint: str):
    from ..store import StoreError, load_entry

    try:
        return load_entry(store / model_id)
    except StoreError as exc:
        raise SystemExit(f"error: model {model_id!r} is not usable in {store} ({exc}); build it with: {hint}") from None


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
    from .. import spare
    from ..config import Settings, default_store, limit_threads
    from . import machine

    blas_threads = Settings().blas_threads
    if blas_threads:  # measure what the server runs: its solves use this many BLAS threads
        limit_threads(blas_threads)
    store = Path(args.store) if args.store else default_store()
    out = Path(args.out)
    (out / "figures").mkdir(parents=True, exist_ok=True)
    results: dict = {
        "machine": {**machine.describe(), "blas_threads": blas_threads, "spare_threads": spare.threads()},
        "started": time.strftime("%Y-%m-%d %H:%M:%S"),
        "parts": {},
    }
    quick = args.quick or args.smoke is not None
    fem_on = not args.no_fem
    parts = [p for p in args.parts if p in PARTS]
    if args.smoke is not None and "minutes" in parts:
        raise SystemExit("error: the minutes part builds scenes (--scenes), not a --smoke model")
    unknown = set(args.parts) - set(PARTS)
    if unknown:
        raise SystemExit(f"error: unknown parts {sorted(unknown)}; choose from {list(PARTS)}")
    liver_hint = "elastreg train benchmarks/scenes/liver_paper.toml (see the README)"
    t_all = time.perf_counter()

    if args.smoke is not None:
        entry = _entry(store, args.smoke, "elastreg train SCENE")
        base = _smoke_case(entry)
        liver_entry = beam_entry = entry
    else:
        needs_liver = set(parts) & {"liver", "pareto", "stability"}
        liver_entry = _entry(store, args.liver_model, liver_hint) if needs_liver else None
        beam_entry = _entry(store, args.beam_model, "elastreg train beam") if "beam" in parts else None
        base = None

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
            results["parts"]["liver"] = liver_part(liver_entry, frames=15 if quick else None,
                                                   own_frames=6 if quick else 20, fem=fem_on, passes=1 if quick else 3)  # fmt: skip

    if "beam" in parts:
        from .beam import beam_part
        from .pareto import plot

        n = 4 if args.smoke is not None else (15 if quick else 60)
        sweep = (dict(gtols=(1e-2,), caps=(5,), points=(50,), fem_gtols=(1e-2,), fem_cases=1, lbfgsb_gtols=(1e-2,),
                      fem_lm_gtols=(1e-2,))
                 if args.smoke is not None else None)  # fmt: skip
        results["parts"]["beam"] = beam_part(beam_entry, n_cases=n, n_points=150 if args.smoke else 500, sweep=sweep)
        plot(
            results["parts"]["beam"]["pareto"], out / "figures" / "beam_pareto.png", "error against run time: the beam"
        )

    if "pareto" in parts:
        from ..store import open_store
        from .cases import liver_paper_case
        from .pareto import pareto_part, plot

        case = base if args.smoke is not None else _first(liver_paper_case(), 12 if quick else 50)
        variants = {}
        if args.smoke is None:
            entries, _ = open_store(store)
            named = {
                args.liver_model: liver_entry,
                **{k: e for k, e in entries.items() if k.startswith(args.liver_model + "_")},
            }
            variants = {_surrogate_label(k, e.manifest["network"]): e.network for k, e in named.items()}
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
        rows = pareto_part(liver_entry, case, variants=variants, **sweep)
        results["parts"]["pareto"] = rows
        plot(rows, out / "figures" / "pareto.png", f"error against run time: {case.name}")

    if "stability" in parts:
        from .cases import liver_paper_case
        from .stability import stability_part

        if args.smoke is not None:
            results["parts"]["stability"] = stability_part(entry, base, frames=1, fem=fem_on, tool_size=4,
                                                           peak_force=0.3 * float(entry.manifest["training"]["load_distribution"]["max_force"]),
                                                           far=0.25 * entry.mesh.size)  # fmt: skip
        else:
            results["parts"]["stability"] = stability_part(
                liver_entry, liver_paper_case(), frames=6 if quick else 12, fem=fem_on
            )

    if "minutes" in parts:
        from ..scene import SceneError, load_scene
        from .minutes import minutes_part
        from .minutes import plot as plot_minutes

        prior = _prior_part(out, "minutes")
        test_data = Path(args.test_data) if args.test_data else Path.home() / ".cache" / "elastreg" / "test-data"

        def save_rows(rows: list[dict]) -> None:  # an hour-long build's row survives a later failure
            (out / "minutes_rows.json").write_text(json.dumps(rows, indent=1))

        try:
            scenes = [load_scene(s) for s in args.scenes] if args.build_minutes else []
        except SceneError as exc:
            raise SystemExit(f"error: {exc} (the default scenes are relative to the repository's root)") from None
        results["parts"]["minutes"] = minutes_part(
            scenes,
            args.build_minutes,
            previous=(prior or {}).get("rows", []),
            test_paths=args.test_paths,
            test_data=test_data,
            workers=args.workers,
            keep=Path(args.keep_store) if args.keep_store else None,
            on_row=save_rows,
        )
        plot_minutes(_latest_minutes(results["parts"]["minutes"]["rows"]), out / "figures" / "build_minutes.png")

    if "anysite" in parts:
        from .anysite import anysite_part, plot_honesty

        if args.smoke is not None:
            results["parts"]["anysite"] = anysite_part(entry, sites=2, frames=2, fem=fem_on, passes=1, truth=args.truth)
        else:
            model = _entry(store, args.anysite_model, f"elastreg train {args.anysite_model}")
            results["parts"]["anysite"] = anysite_part(
                model,
                sites=args.sites,
                frames=4 if quick else 8,
                fem=fem_on,
                passes=1 if quick else 3,
                truth=args.truth,
            )
        results["parts"]["anysite"]["model"] = args.smoke or args.anysite_model
        plot_honesty(results["parts"]["anysite"]["records"], out / "figures" / "anysite_estimates.png")

    results["seconds"] = time.perf_counter() - t_all
    if args.smoke is None:
        results = _merge_previous(results, out)
    write_report(results, out)
    print(f"report written to {out / 'report.md'} ({results['seconds']:.0f} s)")
    return 0


def _surrogate_label(name: str, net: dict) -> str:
    """A variant's name and size, for the Pareto table: 'liver_paper_small (256x256, r 64, 0.2M)'."""
    size = "x".join(str(h) for h in net.get("hidden", []))
    rank = f", r {net['rank']}" if net.get("rank") else ""
    skip = ", physics skip" if net.get("physics_skip") else ""
    return f"{name} ({size}{rank}{skip}, {net.get('parameters', 0) / 1e6:.2f}M parameters)"


def _merge_previous(results: dict, out: Path) -> dict:
    """Keep the parts of the report already in `out` that this run did not redo, so that
    ``elastreg bench beam`` refreshes one part without rerunning the hour-long rest. Each part
    remembers the run that made it."""
    from .cases import FrameRecord

    stamp = {"started": results["started"], "commit": results["machine"]["commit"], "cpu": results["machine"]["cpu"]}
    results["made_by"] = {part: stamp for part in results["parts"]}
    path = out / "results.json"
    if not path.exists():
        return results
    try:
        prior = json.loads(path.read_text())
    except (OSError, ValueError):
        return results
    machine = prior.get("machine", {})
    old_stamp = {"started": prior.get("started"), "commit": machine.get("commit"), "cpu": machine.get("cpu")}
    for part, value in prior.get("parts", {}).items():
        if part in results["parts"] or part not in PARTS:
            continue
        if isinstance(value, dict) and "records" in value:  # per-frame records: back to objects
            value["records"] = [FrameRecord(**r) for r in value["records"]]
        results["parts"][part] = value
        # a stamp from before stamps named the CPU: taken to be the prior run's machine
        results["made_by"][part] = {"cpu": machine.get("cpu"), **prior.get("made_by", {}).get(part, old_stamp)}
    return results


def _prior_part(out: Path, part: str) -> dict | None:
    """A part of the report already in `out`, or None."""
    try:
        return json.loads((out / "results.json").read_text()).get("parts", {}).get(part)
    except (OSError, ValueError):
        return None


def _latest_minutes(rows: list[dict]) -> list[dict]:
    from .minutes import latest

    return latest(rows)


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


def write_report(results: dict, out: Path) -> None:
    """results.json, CSVs, figures and report.md under `out`."""
    parts = results["parts"]
    (out / "results.json").write_text(json.dumps(results, indent=1, default=_jsonable))
    md = ["# elastreg benchmark report\n"]
    m = results["machine"]
    md.append(f"Run {results['started']} on {m['cpu']}, {m['cores']} cores, GPU: {m['gpu'] or 'none'}; "
              f"commit {m['commit']}; sparse solver {m['sparse_solver']}; torch {m['torch']}, numpy {m['numpy']}, "
              f"scipy {m['scipy']}; {m.get('blas_threads') or 'default'} BLAS thread(s) per solve and {m.get('spare_threads', 0)} spare thread(s) beside a frame, as the server runs. Whole run: {results['seconds']:.0f} s. Times are medians over warm frames "
              f"(the first frame of a stream is a cold start).\n")  # fmt: skip
    runs = {(v["started"], v["commit"]) for v in results.get("made_by", {}).values()}
    if len(runs) > 1:
        md.append("Parts come from more than one run (and machine: compare times within a part, not across "
                  "machines): " + "; ".join(f"{part} ({v['started']}, {v['commit']}, {v.get('cpu') or 'CPU not recorded'})"
                                           for part, v in results["made_by"].items()) + ".\n")  # fmt: skip
    if "fem" in parts:
        f = parts["fem"]
        md.append("## FEM (Newton) on the liver\n")
        rows = [{"backend": k, **v} for k, v in f["backends"].items()]
        md.append(_table(rows, [("backend", "solver"), ("largest_from_rest_s", "largest load from rest (s)"),
                                ("largest_iterations", "Newton its"), ("largest_max_displacement_mm", "max disp (mm)"),
                                ("per_iteration_ms", "per iteration (ms)"), ("warm_frame_median_s", "warm frame (s)"),
                                ("warm_iterations_median", "warm its"), ("sequence_max_error_mm", "max error vs FEniCS (mm)")]))  # fmt: skip
        md.append("\nSparse factorisations of the liver's tangent (8,823 dofs):\n\n")
        md.append(_table(f["solvers"], [("backend", "solver"), ("analysis_ms", "analysis (ms)"), ("factor_ms", "numeric factorisation (ms)"),
                                        ("solve_ms", "solve (ms)"), ("residual", "relative residual")]))  # fmt: skip
        _write_csv(out / "fem_solvers.csv", f["solvers"])
    if "liver" in parts:
        L = parts["liver"]
        md.append("\n## Registration (the paper's liver experiment)\n")
        md.append(_table(L["summaries"], [("case", "case"), ("method", "method"), ("frames", "frames"), ("tre_mean_mm", "mean TRE (mm)"),
                                          ("tre_max_mm", "worst frame TRE (mm)"), ("force_error_mean_pct", "force error (%)"),
                                          ("ms_median", "ms / frame"), ("ms_median_passes", "each pass (ms)"), ("ms_p90", "p90 ms"),
                                          ("iterations_mean", "iterations"), ("converged_fraction", "converged")]))  # fmt: skip
        md.append(
            "\nThe network's times: the median over warm frames of each frame's median over the passes, each pass's "
            "median beside it; the Newton method's: one pass.\n"
        )
        md.append(
            "\nThe paper (Titan RTX GPU): network 0.5-3.5 mm TRE at about 140 ms per frame; Newton-based "
            "about 0.1 mm at 14 minutes per frame; force error of the Newton method 10%.\n"
        )
        _write_csv(out / "liver_frames.csv", L["records"])
        _write_csv(out / "liver_summary.csv", L["summaries"])
        _plot_frames(L["records"], out / "figures" / "liver_frames.png")
        md.append("\n![per-frame TRE and time](figures/liver_frames.png)\n")
    if "anysite" in parts:
        A = parts["anysite"]
        md.append(f"\n## Any tool site ({A['model']}): sites the build never aimed at, truth from a finer mesh\n")
        md.append(
            f"Tool patches of {A['tool_nodes']} nodes, supports three times that, sites spread over the whole "
            f"load region; truth: {_TRUTH_TEXT[A.get('truth', 'subdivided')]}"
            + (
                f"; method auto corrects frames whose estimate exceeds {A['max_error_mm']:.3g} mm (twice the "
                "build's validation error) with the Newton method; auto runs the network as its "
                "Levenberg-Marquardt row does where the layout has a Jacobian, and the Newton method, in its "
                "own rows and in auto's corrections, Levenberg-Marquardt (both chosen on calibration sites).\n\n"
                if any(s.get("method") == "auto" for s in A["summaries"])
                else " (network only: run with --no-fem).\n\n"
            )
        )
        md.append(_table(A["summaries"], [("case", "case"), ("method", "method"), ("frames", "frames"),
                                          ("tre_mean_mm", "mean TRE (mm)"), ("force_error_median_pct", "force error, median (%)"),
                                          ("ms_median", "ms / frame"), ("ms_median_passes", "each pass (ms)"),
                                          ("fem_share", "frames by the FEM"), ("converged_fraction", "converged")]))  # fmt: skip
        md.append(
            "\nThe network's times: the median over warm frames of each frame's median over the passes, each pass's "
            "median beside it; auto's and the Newton method's: one pass.\n"
        )
        md.append("\nHow far to trust a frame: each frame's `error_estimate` against its true mean nodal error.\n\n")
        md.append(_table(A["honesty"], [("method", "method"), ("frames", "frames"), ("spearman", "Spearman rho"),
                                        ("under_half", "estimate under half the error"),
                                        ("median_ratio", "median estimate / error")]))  # fmt: skip
        md.append("\n![estimate against true error](figures/anysite_estimates.png)\n")
        _write_csv(out / "anysite_frames.csv", A["records"])
    if "minutes" in parts:
        rows = _latest_minutes(parts["minutes"]["rows"])
        md.append("\n## Validation error against build minutes\n")
        md.append(
            "`elastreg train SCENE --minutes M` from an empty data folder, the whole build on the clock; every "
            "build scored on one held-out test set per scene (the same loads for every budget, a seed no build "
            "uses). Relative error: a sample's displacement error over its displacement, mean and median over "
            "the test samples. The newest row of each scene and budget; every earlier row, with its machine, "
            "commit and load average, is in results.json.\n\n"
        )
        md.append(_table(rows, [("scene", "scene"), ("minutes", "minutes"), ("samples", "samples"), ("wall_s", "wall (s)"),
                                ("test_mean_mm", "test mean (mm)"), ("test_relative", "relative, mean"),
                                ("test_relative_median", "relative, median"), ("test_linear_relative", "linear alone, mean"),
                                ("test_linear_relative_median", "linear alone, median"), ("test_zero_mean_mm", "u = 0 (mm)"),
                                ("load_before", "load average"), ("cpu", "machine"), ("commit", "commit")]))  # fmt: skip
        md.append("\n![relative error against build minutes](figures/build_minutes.png)\n")
    if "beam" in parts:
        b = parts["beam"]["summary"]
        md.append("\n## The beam experiment\n")
        pm = b["paper"]
        lb = b.get("lbfgsb")  # the same cases with the paper's optimizer, if another ran

        def cell(summary: dict, key: str) -> str:
            v = summary[key]
            if key == "ms_median":
                return f"{v:.1f}"
            if key == "ms_median_passes":
                return ", ".join(f"{x:.1f}" for x in v)
            return f"{v[0]:.2e} ± {v[1]:.2e}" if key.endswith("_m") else f"{v[0]:.1f} ± {v[1]:.1f}"

        lines = [
            ("registration error, RMS cloud-to-surface (m)", "rms_distance_m", f"{pm['error'][0]:.0e} ± {pm['error'][1]:.2e}"),
            ("mean nodal error, TRE (m)", "tre_m", "-"),
            ("time (ms)", "ms", f"{pm['ms'][0]:.0f} ± {pm['ms'][1]:.0f}"),
            ("time, median (ms)", "ms_median", "-"),
            ("time, median of each pass (ms)", "ms_median_passes", "-"),
            ("iterations", "iterations", f"{pm['iterations'][0]:.0f} ± {pm['iterations'][1]:.0f}"),
        ]  # fmt: skip
        rows = [{"what": what, "ours": cell(b, key), "paper": paper, **({"lbfgsb": cell(lb, key)} if lb else {})}
                for what, key, paper in lines if key in b]  # fmt: skip
        cols = [("what", ""), ("ours", "elastreg (2 CPU cores)"), ("paper", "paper (GPU)")]
        if lb:
            cols.insert(2, ("lbfgsb", "elastreg, L-BFGS-B"))
        optimizer = b.get("config", {}).get("optimizer", "lbfgsb")
        md.append(f"{b['cases']} deformations (bending, torsion, both; largest displacement "
                  f"{b['max_displacement_m'][0] * 1e3:.1f} ± {b['max_displacement_m'][1] * 1e3:.1f} mm), "
                  f"each registered from rest by the network method"
                  + (f" over {b['unknowns']} force unknowns (gtol {b['config']['gtol']:g}, "
                     + ("Levenberg-Marquardt through the network's Jacobian" if optimizer == "levenberg-marquardt" else
                        f"L-BFGS-B, Gauss-Newton preconditioning {'on' if b['config']['precondition'] else 'off'}")
                     + ")" if "config" in b else "")
                  + f"; converged {b['converged_fraction']:.0%}"
                  + (f" (L-BFGS-B with the Gauss-Newton preconditioner: {lb['converged_fraction']:.0%})" if lb else "")
                  + ".\n\n")  # fmt: skip
        md.append(_table(rows, cols))
        _write_csv(out / "beam.csv", parts["beam"]["rows"])
        if parts["beam"].get("pareto"):
            md.append("\n### Error against run time on the beam\n\n![beam Pareto chart](figures/beam_pareto.png)\n\n"
                      "The first 20 cases (the Newton method: the first 6, at most 10 s each); force error: the "
                      "resultant's error over the total applied load (numbers also in beam_pareto.csv):\n\n")  # fmt: skip
            md.append(_table(parts["beam"]["pareto"], [("method", "method"), ("knob", "knob"), ("value", "value"), ("tre_mm", "mean TRE (mm)"),
                                                       ("force_error_pct", "force error (%)"), ("ms", "ms / registration"),
                                                       ("iterations", "iterations"), ("converged", "converged")]))  # fmt: skip
            _write_csv(out / "beam_pareto.csv", parts["beam"]["pareto"])
    if "pareto" in parts:
        from .pareto import pareto_front

        rows = parts["pareto"]
        md.append("\n## Error against run time\n")
        md.append(
            "![Pareto chart](figures/pareto.png)\n\nEvery point (numbers also in pareto.csv; ms / frame: the median over "
            "warm frames of each frame's median over the passes, each pass's own median beside it):\n\n"
        )
        md.append(_table(rows, [("method", "method"), ("knob", "knob"), ("value", "value"), ("tre_mm", "mean TRE (mm)"),
                                ("force_error_pct", "force error (%)"), ("ms", "ms / frame"), ("ms_passes", "each pass (ms)"),
                                ("iterations", "iterations"), ("converged", "converged")]))  # fmt: skip
        for method in dict.fromkeys(r["method"] for r in rows if not r["method"].startswith("fem")):
            front = pareto_front([r for r in rows if r["method"] == method])
            md.append(f"\nPareto front (TRE), {method}: "
                      + ", ".join(f"{r['knob']}={r['value']}: {r['tre_mm']:.3f} mm @ {r['ms']:.1f} ms" for r in front) + "\n")  # fmt: skip
        _write_csv(out / "pareto.csv", rows)
    if "stability" in parts:
        rows = parts["stability"]["rows"]
        md.append("\n## Stability on stiff and extreme cases\n")
        md.append(_table(rows, [("case", "case"), ("method", "method"), ("frames_made", "frames"), ("converged_fraction", "converged"),
                                ("tre_mean_mm", "mean TRE (mm)"), ("force_error_mean_pct", "force error (%)"), ("ms_median", "ms / frame"),
                                ("all_finite", "no NaN"), ("crashed", "crashed"), ("statuses", "statuses")]))  # fmt: skip
        short = [r for r in rows if not r.get("crashed") and r.get("converged_fraction", 1.0) < 1.0]
        if short:
            md.append("\nNot converged on every frame (the fraction that did, and why the others stopped; "
                      "`time_limit` is the Newton method's 10 s budget per frame): "
                      + "; ".join(f"{r['case']} / {r['method']}: {r['converged_fraction']:.0%} "
                                  f"({', '.join(s for s in r.get('statuses', []) if s != 'converged')})" for r in short)
                      + ".\n")  # fmt: skip
        bad = [r for r in rows if r.get("crashed") or not r.get("all_finite", True)]
        md.append("\n" + ("Every case ran without a crash or a NaN.\n" if not bad else
                         "Cases that crashed or produced NaN: " + ", ".join(f"{r['case']} / {r['method']}" for r in bad) + "\n"))  # fmt: skip
        _write_csv(out / "stability.csv", rows)
    (out / "report.md").write_text("\n".join(md))


def _plot_frames(records, path: Path) -> None:
    matplotlib = need("matplotlib", "the benchmark's figures")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = list(dict.fromkeys(r.case for r in records))
    fig, axes = plt.subplots(2, len(cases), figsize=(4.2 * len(cases), 6), squeeze=False)
    for j, case in enumerate(cases):
        for method, colour in (("none (rest shape)", "grey"), ("network", "tab:blue"), ("network, levenberg-marquardt", "tab:green"),
                               ("network, levenberg-marquardt, gtol 3e-3", "tab:olive"),
                               ("fem", "tab:red"), ("fem, levenberg-marquardt", "tab:purple")):  # fmt: skip
            rs = [r for r in records if r.case == case and r.method == method]
            if not rs:
                continue
            axes[0, j].plot([r.frame for r in rs], [r.tre_mm for r in rs], color=colour, label=method)
            if method != "none (rest shape)":
                axes[1, j].plot([r.frame for r in rs], [r.ms for r in rs], color=colour, label=method)
        axes[0, j].set_title(case, fontsize=9)
        axes[0, j].set_yscale("log")
        axes[0, j].set_ylabel("mean TRE (mm)")
        axes[1, j].set_yscale("log")
        axes[1, j].set_ylabel("ms per frame")
        axes[1, j].set_xlabel("frame")
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

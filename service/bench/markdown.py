"""The benchmark report: report.md, a section per part (its tables, its figure), each part's
CSV written beside it, and results.json (:mod:`.results`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .results import write_csv, write_minutes_rows, write_results

_TRUTH_TEXT = {
    "subdivided": "the Neo-Hookean solution on the mesh subdivided once",
    "quadratic": "the Neo-Hookean solution on ten-node tets of the mesh (a uniform traction over the tool "
    "patch's triangles)",
}


def held_out_words(held: int, sites: int) -> tuple[str, str]:
    """The any-site heading's words and its body's for `held` of `sites` sites whose supports
    the build kept every training load off (the case names say which)."""
    if held == 0:
        return "loads", (
            "load region, so inside the region the build was trained on (the loads and the truth are held out, "
            "not the sites)"
        )
    heading = "sites and loads" if held == sites else f"{held} of {sites} sites, and loads,"
    return heading, (
        f"load region; {held} of the {sites} sites held out of the build (no training load touched their supports: "
        "[training] keep_off), the loads and the truth held out at every site"
    )


def fmt(v, digits: int = 3) -> str:
    if isinstance(v, (list, tuple)):  # a cell of several figures (each pass's time, statuses)
        return ", ".join(fmt(x, digits) for x in v)
    if isinstance(v, float):
        if not np.isfinite(v):
            return str(v)
        return f"{v:.{digits}g}" if abs(v) < 1e-2 or abs(v) >= 1e4 else f"{v:.{digits}f}".rstrip("0").rstrip(".")
    return str(v)


def _test_set(row: dict) -> str:
    """A minutes row's test set: its samples and its loads' hash, where recorded."""
    if row.get("test_samples") is None:
        return "not recorded"
    return f"{row['test_samples']}, {row.get('test_loads') or 'loads not recorded'}"


def table(rows: list[dict], cols: list[tuple[str, str]]) -> str:
    head = "| " + " | ".join(label for _, label in cols) + " |\n|" + "---|" * len(cols) + "\n"
    return head + "".join("| " + " | ".join(fmt(r.get(k, "")) for k, _ in cols) + " |\n" for r in rows)


def write_report(results: dict, out: Path) -> None:
    """results.json, CSVs, figures and report.md under `out`."""
    parts = results["parts"]
    write_results(results, out)
    md = ["# elastreg benchmark report\n"]
    m = results["machine"]
    md.append(f"Run {results['started']} on {m['cpu']}, {m['cores']} cores, GPU: {m['gpu'] or 'none'}; "
              f"commit {m['commit']}; sparse solver {m['sparse_solver']}; torch {m['torch']}, numpy {m['numpy']}, "
              f"scipy {m['scipy']}; {m.get('blas_threads') or 'default'} BLAS thread(s) per solve and {m.get('spare_threads', 0)} spare thread(s) beside a frame, as the server runs. Whole run: {results['seconds']:.0f} s. Times are medians over warm frames "
              f"(the first frame of a stream is a cold start).\n")  # fmt: skip
    if results.get("smoke"):
        md.append(f"A --smoke run on the tiny model {results['smoke']!r}: it runs every code path, its figures "
                  "measure nothing.\n")  # fmt: skip
    runs = {(v["started"], v["commit"]) for v in results.get("made_by", {}).values()}
    if len(runs) > 1:
        md.append("Parts come from more than one run (and machine: compare times within a part, not across "
                  "machines): " + "; ".join(f"{part} ({v['started']}, {v['commit']}, {v.get('cpu') or 'CPU not recorded'}"
                                           f"{', --quick' if v.get('quick') else ''})"
                                           for part, v in results["made_by"].items()) + ".\n")  # fmt: skip
    quick = [part for part, v in results.get("made_by", {}).items() if v.get("quick")]
    if quick and not results.get("smoke"):  # a smoke run is quick throughout, and says so above
        md.append(f"Run with --quick (fewer frames and sweep points than a full run, their figures not a full run's): "
                  f"{', '.join(quick)}.\n")  # fmt: skip
    if "fem" in parts:
        f = parts["fem"]
        md.append("## FEM (Newton) on the liver\n")
        rows = [{"backend": k, **v} for k, v in f["backends"].items()]
        md.append(table(rows, [("backend", "solver"), ("largest_from_rest_s", "largest load from rest (s)"),
                                ("largest_iterations", "Newton its"), ("largest_max_displacement_mm", "max disp (mm)"),
                                ("per_iteration_ms", "per iteration (ms)"), ("warm_frame_median_s", "warm frame (s)"),
                                ("warm_iterations_median", "warm its"), ("sequence_max_error_mm", "max error vs FEniCS (mm)")]))  # fmt: skip
        md.append("\nSparse factorisations of the liver's tangent (8,823 dofs):\n\n")
        md.append(table(f["solvers"], [("backend", "solver"), ("analysis_ms", "analysis (ms)"), ("factor_ms", "numeric factorisation (ms)"),
                                        ("solve_ms", "solve (ms)"), ("residual", "relative residual")]))  # fmt: skip
        write_csv(out / "fem_solvers.csv", f["solvers"])
    if "liver" in parts:
        L = parts["liver"]
        md.append("\n## Registration (the paper's liver experiment)\n")
        md.append(table(L["summaries"], [("case", "case"), ("method", "method"), ("frames", "frames"), ("tre_mean_mm", "mean TRE (mm)"),
                                          ("tre_max_mm", "worst frame TRE (mm)"), ("failed_frames", "failed frames"), ("force_error_mean_pct", "force error (%)"),
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
        write_csv(out / "liver_frames.csv", L["records"])
        write_csv(out / "liver_summary.csv", L["summaries"])
        from .liver import plot_frames

        plot_frames(L["records"], out / "figures" / "liver_frames.png")
        md.append("\n![per-frame TRE and time](figures/liver_frames.png)\n")
    if "anysite" in parts:
        A = parts["anysite"]
        held, where = held_out_words(A.get("held_out_sites", 0), len({s["case"] for s in A["summaries"]}))
        md.append(
            f"\n## Any tool site ({A['model']}): sites spread over the surface, {held} held out, truth from a finer mesh\n"
        )
        built = A.get("model_entry")  # which build: reports before it named the id alone
        md.append(
            (f"The build of {built['created']} (weights sha256 {str(built['weights_sha256'])[:12]}). " if built else "")
            + f"Tool patches of {A['tool_nodes']} nodes, supports three times that, sites spread over the whole "
            + where
            + f"; truth: {_TRUTH_TEXT[A.get('truth', 'subdivided')]}"
            + (
                f"; method auto corrects frames whose estimate exceeds {A['max_error_mm']:.3g} mm (twice the "
                "build's validation error) with the Newton method; auto runs the network as its "
                "Levenberg-Marquardt row does where the layout has a Jacobian, and the Newton method, in its "
                "own rows and in auto's corrections, Levenberg-Marquardt (both chosen on the liver's calibration sites, "
                "which overlapped its reported ones: docs/performance.md).\n\n"
                if any(s.get("method") == "auto" for s in A["summaries"])
                else " (network only: run with --no-fem).\n\n"
            )
        )
        md.append(table(A["summaries"], [("case", "case"), ("method", "method"), ("frames", "frames"),
                                          ("tre_mean_mm", "mean TRE (mm)"), ("failed_frames", "failed frames"), ("force_error_median_pct", "force error, median (%)"),
                                          ("ms_median", "ms / frame"), ("ms_median_passes", "each pass (ms)"),
                                          ("fem_share", "frames by the FEM"), ("converged_fraction", "converged")]))  # fmt: skip
        md.append(
            "\nThe network's times: the median over warm frames of each frame's median over the passes, each pass's "
            "median beside it; auto's and the Newton method's: one pass.\n"
        )
        md.append("\nHow far to trust a frame: each frame's `error_estimate` against its true mean nodal error.\n\n")
        md.append(table(A["honesty"], [("method", "method"), ("frames", "frames"), ("spearman", "Spearman rho"),
                                        ("under_half", "estimate under half the error"),
                                        ("median_ratio", "median estimate / error")]))  # fmt: skip
        md.append("\n![estimate against true error](figures/anysite_estimates.png)\n")
        write_csv(out / "anysite_frames.csv", A["records"])
    if "minutes" in parts:
        from .minutes import latest, left_out  # here: the minutes part imports the whole build

        rows = [{**r, "test_set": _test_set(r)} for r in latest(parts["minutes"]["rows"])]
        apart = left_out(parts["minutes"]["rows"])
        write_minutes_rows(out, parts["minutes"]["rows"])
        md.append("\n## Validation error against build minutes\n")
        md.append(
            "`elastreg train SCENE --minutes M` from an empty data folder, the whole build on the clock; every "
            "build scored on one held-out test set per scene (the same loads for every budget, a seed no build "
            "uses). Relative error: a sample's displacement error over its displacement, mean and median over "
            "the test samples. The newest row of each scene and budget; every earlier row, with its machine, "
            "commit and load average, is in results.json.\n\n"
        )
        md.append(table(rows, [("scene", "scene"), ("minutes", "minutes"), ("samples", "samples"), ("wall_s", "wall (s)"),
                                ("test_mean_mm", "test mean (mm)"), ("test_relative", "relative, mean"),
                                ("test_relative_median", "relative, median"), ("test_linear_relative", "linear alone, mean"),
                                ("test_linear_relative_median", "linear alone, median"), ("test_zero_mean_mm", "u = 0 (mm)"),
                                ("load_before", "load average"), ("cpu", "machine"), ("commit", "commit"),
                                ("test_set", "test set (samples, loads' hash)")]))  # fmt: skip
        if apart:  # a curve is one machine's builds on one test set: the scene's newest row's
            md.append("\nLeft out of the table and the figure, built on another machine or scored on another test set "
                      "than their scene's newest row: " + "; ".join(f"{r['scene']} at {fmt(r['minutes'])} minutes "
                      f"({r.get('cpu') or 'CPU not recorded'}, test set {_test_set(r)})" for r in apart) + ".\n")  # fmt: skip
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
        md.append(table(rows, cols))
        write_csv(out / "beam.csv", parts["beam"]["rows"])
        if parts["beam"].get("pareto"):
            md.append("\n### Error against run time on the beam\n\n![beam Pareto chart](figures/beam_pareto.png)\n\n"
                      "The first 20 cases (the Newton method: the first 6, at most 10 s each); force error: the "
                      "resultant's error over the total applied load (numbers also in beam_pareto.csv):\n\n")  # fmt: skip
            md.append(table(parts["beam"]["pareto"], [("method", "method"), ("knob", "knob"), ("value", "value"), ("tre_mm", "mean TRE (mm)"),
                                                       ("force_error_pct", "force error (%)"), ("ms", "ms / registration"),
                                                       ("iterations", "iterations"), ("converged", "converged")]))  # fmt: skip
            write_csv(out / "beam_pareto.csv", parts["beam"]["pareto"])
    if "pareto" in parts:
        from .pareto import pareto_front

        rows = parts["pareto"]
        md.append("\n## Error against run time\n")
        md.append(
            "![Pareto chart](figures/pareto.png)\n\nEvery point (numbers also in pareto.csv; ms / frame: the median over "
            "warm frames of each frame's median over the passes, each pass's own median beside it):\n\n"
        )
        md.append(table(rows, [("method", "method"), ("knob", "knob"), ("value", "value"), ("tre_mm", "mean TRE (mm)"),
                                ("force_error_pct", "force error (%)"), ("ms", "ms / frame"), ("ms_passes", "each pass (ms)"),
                                ("iterations", "iterations"), ("converged", "converged"), ("failed_frames", "failed frames")]))  # fmt: skip
        for method in dict.fromkeys(r["method"] for r in rows if not r["method"].startswith("fem")):
            front = pareto_front([r for r in rows if r["method"] == method])
            md.append(f"\nPareto front (TRE), {method}: "
                      + ", ".join(f"{r['knob']}={r['value']}: {r['tre_mm']:.3f} mm @ {r['ms']:.1f} ms" for r in front) + "\n")  # fmt: skip
        write_csv(out / "pareto.csv", rows)
    if "stability" in parts:
        rows = parts["stability"]["rows"]
        md.append("\n## Stability on stiff and extreme cases\n")
        md.append(table(rows, [("case", "case"), ("method", "method"), ("frames_made", "frames"), ("converged_fraction", "converged"),
                                ("tre_mean_mm", "mean TRE (mm)"), ("force_error_mean_pct", "force error (%)"), ("ms_median", "ms / frame"),
                                ("all_finite", "no NaN"), ("failed_frames", "failed frames"), ("crashed", "crashed"), ("statuses", "statuses")]))  # fmt: skip
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
        write_csv(out / "stability.csv", rows)
    (out / "report.md").write_text("\n".join(md))

"""The benchmark's every part on a tiny model, in seconds: so the report cannot rot."""

import json
import shutil
from pathlib import Path

import pytest

from service.cli import main
from tests.conftest import interrupt

#: the committed report of full runs (the default --out), copied where a test needs one
LATEST = Path(__file__).resolve().parents[2] / "reports" / "latest"


def files(folder: Path) -> dict[str, bytes]:
    """Every file under `folder` by its relative path, with its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_bench_smoke_writes_the_whole_report(bar_store, tmp_path):
    store, _ = bar_store
    out = tmp_path / "report"
    assert main(["bench", "--smoke", "bar", "--store", str(store), "--out", str(out)]) == 0
    results = json.loads((out / "results.json").read_text())
    assert set(results["parts"]) == {"fem", "liver", "beam", "pareto", "stability", "anysite"}
    report = (out / "report.md").read_text()
    for heading in (
        "FEM (Newton)",
        "Registration",
        "beam experiment",
        "Error against run time",
        "Stability",
        "Any tool site",
    ):
        assert heading in report
    assert (out / "figures" / "pareto.png").stat().st_size > 1000
    assert (out / "figures" / "liver_frames.png").stat().st_size > 1000
    assert (out / "figures" / "beam_pareto.png").stat().st_size > 1000
    beam = results["parts"]["beam"]["pareto"]  # both methods, and both optimizers, on the beam's sweep
    assert {r["method"] for r in beam} == {"network, levenberg-marquardt", "network", "fem", "fem, levenberg-marquardt"}
    assert "on the beam" in report
    liver = results["parts"]["pareto"]
    assert {r["method"] for r in liver} == {
        "network",
        "network, levenberg-marquardt",
        "fem",
        "fem, levenberg-marquardt",
    }
    # each point timed over passes (two in the smoke run), each pass's median kept beside it
    assert all(len(r["ms_passes"]) == 2 for r in liver) and "each pass (ms)" in report
    summary = results["parts"]["beam"]["summary"]  # Levenberg-Marquardt, and L-BFGS-B beside it
    assert summary["config"]["optimizer"] == "levenberg-marquardt" and summary["lbfgsb"]["cases"] == summary["cases"]
    assert "elastreg, L-BFGS-B" in report
    # three passes over the same cases, for each optimizer: the time is their median, each kept
    assert len(summary["ms_median_passes"]) == 3 and len(summary["lbfgsb"]["ms_median_passes"]) == 3
    assert all(len(r["ms_passes"]) == 3 for r in results["parts"]["beam"]["rows"])
    assert "median of each pass" in report
    for s in results["parts"]["liver"]["summaries"]:
        assert s["all_finite"]
    net = next(s for s in results["parts"]["liver"]["summaries"] if s["method"] == "network")
    rest = next(s for s in results["parts"]["liver"]["summaries"] if s["method"] == "none (rest shape)")
    assert net["tre_mean_mm"] < rest["tre_mean_mm"]  # registration beats doing nothing
    lm = next(s for s in results["parts"]["liver"]["summaries"] if s["method"] == "network, levenberg-marquardt")
    whole = next(s for s in results["parts"]["liver"]["summaries"] if s["method"].endswith("gtol 3e-3"))
    assert whole["frames"] == net["frames"] and whole["tre_mean_mm"] < rest["tre_mean_mm"]
    assert lm["frames"] == net["frames"] and lm["tre_mean_mm"] < rest["tre_mean_mm"]
    fem_lm = next(s for s in results["parts"]["liver"]["summaries"] if s["method"] == "fem, levenberg-marquardt")
    assert fem_lm["frames"] == net["frames"] and fem_lm["tre_mean_mm"] < rest["tre_mean_mm"]
    assert {r["method"] for r in results["parts"]["stability"]["rows"]} >= {"fem", "fem, levenberg-marquardt"}
    assert not any(r.get("crashed") for r in results["parts"]["stability"]["rows"])
    assert results["parts"]["fem"]["backends"]  # at least one solver ran
    anysite = results["parts"]["anysite"]  # two sites, truth from the subdivided bar
    lm = "network, levenberg-marquardt"  # the smoke model is reduced: it has a Jacobian
    assert {s["method"] for s in anysite["summaries"]} == {"none (rest shape)", "network", lm, "auto", "fem"}
    assert {h["method"] for h in anysite["honesty"]} == {"network", lm, "auto", "fem"}
    assert all(-1 <= h["spearman"] <= 1 for h in anysite["honesty"])
    assert all(r["error_estimate_mm"] > 0 for r in anysite["records"] if r["method"] in ("network", lm))
    timed = {s["method"]: s.get("ms_median_passes") for s in anysite["summaries"]}
    assert len(timed["network"]) == 1 and len(timed[lm]) == 1  # the smoke run's one pass, recorded
    assert timed["fem"] is None and timed["auto"] is None  # one pass of seconds-long frames: not listed
    assert (out / "figures" / "anysite_estimates.png").stat().st_size > 1000
    manifest = json.loads((store / "bar" / "manifest.json").read_text())  # which build ran, not only its id
    assert anysite["model_entry"]["weights_sha256"] == manifest["files"]["weights.safetensors"]
    assert anysite["model_entry"]["created"] == manifest["created"]


def test_a_smoke_run_never_replaces_a_report_of_full_runs(bar_store, tmp_path, capsys):
    """`bench --smoke MODEL` into a folder holding a full report (the default --out is
    reports/latest) kept only its smoke part: results.json lost every other part and report.md
    shrank from 240 lines to 19. A smoke run's figures are not comparable with a full run's, so
    it refuses such a folder: one line, exit status 2, not a byte changed."""
    out = tmp_path / "latest"
    shutil.copytree(LATEST, out)
    before = files(out)
    with pytest.raises(SystemExit) as exit_:
        main(["bench", "fem", "--smoke", "bar", "--store", str(bar_store[0]), "--out", str(out)])
    err = capsys.readouterr().err
    refusal = (
        f"error: {out} holds a report of full runs, which a --smoke run's figures would mix with: give another --out, "
        "or --replace to replace it"
    )
    assert exit_.value.code == 2 and err == refusal + "\n", err
    assert files(out) == before


def test_replace_lets_a_smoke_run_replace_a_report_of_full_runs(bar_store, tmp_path):
    """No flag let a user put a smoke report where a full one was on purpose: --replace does,
    and the folder is replaced whole (no file of the full report stays beside the smoke one)."""
    out = tmp_path / "latest"
    shutil.copytree(LATEST, out)
    assert main(["bench", "fem", "--smoke", "bar", "--store", str(bar_store[0]), "--out", str(out), "--replace"]) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["smoke"] == "bar" and set(results["parts"]) == {"fem"} and set(results["made_by"]) == {"fem"}
    assert sorted(files(out)) == ["fem_solvers.csv", "report.md", "results.json"]
    assert not list(tmp_path.glob(".bench-*"))


def test_ctrl_c_leaves_the_report_as_it_was_and_is_one_line(bar_store, tmp_path):
    """Ctrl-C during a later part left the figures the run had drawn beside the old run's
    results.json and report.md, and a KeyboardInterrupt traceback. The run's files now change
    together when it writes its results: Ctrl-C leaves the report as it was (no scratch left
    behind) and answers one line, `interrupted`, exit status 130, as `train` and `demo` do."""
    smoke = ["bench", "--smoke", "bar", "--store", str(bar_store[0]), "--out", str(tmp_path / "report")]
    assert main([*smoke, "beam"]) == 0  # the report there: the beam part, its figure drawn
    before = files(tmp_path / "report")
    # stopped in the stability part, once the beam's and the Pareto part's figures are drawn
    status, text = interrupt(["-v", *smoke, "beam", "pareto", "stability"], "service.bench.stability: stability ")
    assert status == 130 and "Traceback" not in text, text[-3000:]
    assert text.rstrip().splitlines()[-1] == "interrupted", text[-3000:]
    assert files(tmp_path / "report") == before and not list(tmp_path.glob(".bench-*"))


def test_a_report_keeps_parts_only_from_a_run_of_its_kind(tmp_path):
    """merge_previous keeps an earlier smoke run's parts for a smoke run, never for a full one
    (nor a full run's for a smoke one): each report holds one kind of figures."""
    from service.bench.results import merge_previous

    def run(smoke, parts):
        return {"started": "now", "smoke": smoke, "machine": {"commit": "c", "cpu": "x"}, "parts": parts}

    (tmp_path / "results.json").write_text(json.dumps(run("bar", {"fem": {"backends": []}})))
    assert set(merge_previous(run("bar", {"beam": {}}), tmp_path)["parts"]) == {"fem", "beam"}
    assert set(merge_previous(run(None, {"beam": {}}), tmp_path)["parts"]) == {"beam"}
    full = {k: v for k, v in run(None, {"fem": {"backends": []}}).items() if k != "smoke"}  # as committed reports
    (tmp_path / "results.json").write_text(json.dumps(full))
    assert set(merge_previous(run("bar", {"beam": {}}), tmp_path)["parts"]) == {"beam"}


def test_passes_take_the_same_steps_and_time_each_frame_by_its_median(entry):
    """run_passes: a pass's records with each frame's time its median over the passes (one
    run's steps: the passes are the same registration), and each pass's median time."""
    from service.bench.cases import run_case, run_passes
    from service.bench.liver import NETWORK
    from service.bench.parts import smoke_case

    case = smoke_case(entry)
    records, each = run_passes(entry.network, case, NETWORK, 3)
    single = run_case(entry.network, case, NETWORK)
    assert len(each) == 3 and len(records) == case.frames == len(single)
    assert [r.iterations for r in records] == [r.iterations for r in single]
    assert [r.tre_mm for r in records] == [r.tre_mm for r in single]
    assert all(r.ms > 0 for r in records)
    with pytest.raises(ValueError, match="passes must be at least 1"):
        run_passes(entry.network, case, NETWORK, 0)


def test_a_frames_force_error_splits_along_and_across_the_truth(entry):
    """force_along_pct: the answer's net force along the true one (% of it); its gap to 100 is
    the part of the force error along the truth, so it never exceeds the whole, and the rest of
    the error lies across it."""
    from service.bench.cases import run_case
    from service.bench.liver import NETWORK
    from service.bench.parts import smoke_case

    case = smoke_case(entry)
    records = run_case(entry.network, case, NETWORK)
    assert records and all(r.force_along_pct is not None for r in records)
    for r in records:
        assert abs(r.force_along_pct - 100) <= r.force_error_pct * (1 + 1e-12)
    assert any(50 < r.force_along_pct < 150 for r in records)  # the smoke model finds the pull


def test_a_streamed_case_scores_as_run_case_does(entry):
    """stream_case gives each frame's result (its displacement for a driver's own comparison) and
    score makes run_case's record from it, the frame's objective included."""
    from service.bench.cases import run_case, score, stream_case
    from service.bench.liver import NETWORK
    from service.bench.parts import smoke_case

    case = smoke_case(entry)
    streamed = list(stream_case(entry.network, case, NETWORK))
    assert len(streamed) == case.frames and all(r.outputs["displacement"].shape == case.mesh.nodes.shape
                                                for r, _ in streamed)  # fmt: skip
    records = [score(case, k, r, ms, "network") for k, (r, ms) in enumerate(streamed)]
    again = run_case(entry.network, case, NETWORK)
    assert [r.tre_mm for r in records] == [r.tre_mm for r in again]
    assert [r.objective for r in records] == [r.objective for r in again] == [r.objective for r, _ in streamed]
    assert all(r.objective is not None and 0 < r.objective < 1e-3 for r in records)  # m^2: under 30 mm rms


def test_passes_that_take_other_steps_are_refused():
    """same_steps: timing over passes is refused when a pass took other steps than the first
    (a registration that is not deterministic would mix two different works' times)."""
    from service.bench.cases import same_steps

    counts = iter([[3, 4], [3, 4], [3, 5]])
    with pytest.raises(RuntimeError, match="took different steps"):
        same_steps(lambda: next(counts), 3, lambda r: r, "a case")
    runs = same_steps(lambda: [3, 4], 2, lambda r: r, "a case")
    assert runs == [[3, 4], [3, 4]]


def test_merged_parts_say_which_machine_made_them(tmp_path):
    """A part kept from an earlier run keeps that run's CPU in its stamp (read from the run's
    machine where its stamp predates CPUs)."""
    from service.bench.results import merge_previous

    prior = {"started": "then", "machine": {"commit": "abc", "cpu": "AMD EPYC"},
             "parts": {"fem": {"backends": []}, "pareto": []},
             "made_by": {"fem": {"started": "then", "commit": "abc"}}}  # fmt: skip
    (tmp_path / "results.json").write_text(json.dumps(prior))
    now = {"started": "now", "machine": {"commit": "def", "cpu": "Intel Xeon"}, "parts": {"beam": {}}}
    merged = merge_previous(now, tmp_path)
    assert merged["made_by"]["beam"] == {"started": "now", "commit": "def", "cpu": "Intel Xeon", "quick": False}
    assert merged["made_by"]["fem"] == {"started": "then", "commit": "abc", "cpu": "AMD EPYC"}
    assert merged["made_by"]["pareto"]["cpu"] == "AMD EPYC"  # no stamp at all: the run's own


def test_a_quick_part_merged_into_a_full_report_says_so(bar_store, tmp_path):
    """`bench beam --quick` into a report of full runs merged its 15 cases over the full run's 60
    unmarked: results.json had no trace of --quick, nor report.md. A run now records it, each
    part's stamp carries it, and the report names the parts run with --quick."""
    from service.bench.markdown import write_report
    from service.bench.results import merge_previous

    out = tmp_path / "smoke"
    assert main(["bench", "fem", "--smoke", "bar", "--store", str(bar_store[0]), "--out", str(out), "--quick"]) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["quick"] is True and results["made_by"]["fem"]["quick"] is True
    full = json.loads((LATEST / "results.json").read_text())
    folder = tmp_path / "latest"
    (folder / "figures").mkdir(parents=True)
    (folder / "results.json").write_text(json.dumps(full))
    now = {"started": "now", "quick": True, "machine": {**full["machine"], "commit": "def"}, "seconds": 1.0,
           "parts": {"beam": full["parts"]["beam"]}}  # fmt: skip
    merged = merge_previous(now, folder)
    assert merged["made_by"]["beam"]["quick"] is True and not merged["made_by"]["liver"].get("quick")
    write_report(merged, folder)
    report = (folder / "report.md").read_text()
    assert (
        "Run with --quick (fewer frames and sweep points than a full run, their figures not a full run's): beam."
        in report
    )
    assert "beam (now, def, " in report and ", --quick)" in report


def test_the_cpu_is_named_with_its_generation():
    """A VM may name only the vendor's line ("AMD EPYC"): the report's CPU also gives its family,
    model and cache where the system tells them, so two generations of one name differ."""
    from pathlib import Path

    from service.bench.machine import _cpu_model

    name = _cpu_model()
    assert name
    info = Path("/proc/cpuinfo")
    if info.exists() and "cpu family" in info.read_text():
        assert "family" in name and "model" in name

"""`elastreg bench`'s flags: an impossible value is one line naming the flag and exit status 2
at parse time, before the report folder, a test set or a build is touched."""

import argparse
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from service.cli import main, parser
from tests.conftest import needs_liver

#: the shipped store: the beam and the phantom, each the wrong model for the other's parts
STORE = Path(__file__).resolve().parents[2] / "model_store"


@pytest.mark.parametrize(
    "argv, words",
    [
        # each was a traceback from the build (0 and -1 after the test set was solved; nan in training)
        (["minutes", "--build-minutes", "-1"], "--build-minutes: must be a positive finite number, got '-1'"),
        (["minutes", "--build-minutes", "0"], "--build-minutes: must be a positive finite number, got '0'"),
        (["minutes", "--build-minutes", "5", "nan"], "--build-minutes: must be a positive finite number, got 'nan'"),
        (["minutes", "--build-minutes", "inf"], "--build-minutes: must be a positive finite number, got 'inf'"),
        (["minutes", "--build-minutes", "1e308"], "--build-minutes: must be at most 525600 (a year), got '1e308'"),
        # a FileNotFoundError traceback, after writing an empty test set into the cache
        (["minutes", "--test-paths", "0"], "--test-paths: must be a whole number >= 1, got '0'"),
        (["minutes", "--workers", "-1"], "--workers: must be a whole number >= 0, got '-1'"),  # 33 s, then a traceback
        (["anysite", "--sites", "0"], "--sites: must be a whole number >= 1, got '0'"),  # ran one site
        (["anysite", "--sites", "-2"], "--sites: must be a whole number >= 1, got '-2'"),
        (["anysite", "--sites", "2.5"], "--sites: must be a whole number >= 1, got '2.5'"),
        # made the report's figures folder, then refused
        (["nonsense"], "argument parts: unknown part 'nonsense'; choose from fem, liver, beam, pareto, stability"),
        # a model is a store entry's folder: a path out of the store loaded whatever it named there
        (["beam", "--beam-model", "../model_store/beam"], "--beam-model: model id '../model_store/beam' must start"),
        (["anysite", "--anysite-model", "sub/phantom"], "--anysite-model: model id 'sub/phantom' must start"),
        (["liver", "--liver-model", ".."], "--liver-model: model id '..' must start with a letter or digit"),
        (["pareto", "--liver-model", ""], "--liver-model: model id '' must start with a letter or digit"),
        (["--smoke", "tiny model"], "--smoke: model id 'tiny model' must start with a letter or digit and hold only"),
        (["beam", "--beam-model", "bèam"], "--beam-model: model id 'bèam' must start with a letter or digit and hold"),
    ],
)
def test_impossible_bench_flags_are_refused_before_any_work(argv, words, tmp_path, capsys):
    out, test_data = tmp_path / "report", tmp_path / "test-data"
    elsewhere = ["--scenes", str(tmp_path / "no.toml"), "--store", str(tmp_path / "no-store")]  # a run fails fast
    with pytest.raises(SystemExit) as exit_:
        main(["bench", *argv, "--out", str(out), "--test-data", str(test_data), *elsewhere])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and words in err, err
    assert "Traceback" not in err and not out.exists() and not test_data.exists()


def test_the_bench_flags_edge_values_parse():
    args = parser().parse_args(["bench", "minutes", "--build-minutes", "0.2", "60", "--test-paths", "1",
                                "--workers", "0", "--sites", "1"])  # fmt: skip
    assert (args.build_minutes, args.test_paths, args.workers, args.sites) == ([0.2, 60.0], 1, 0, 1)
    assert parser().parse_args(["bench", "minutes", "--build-minutes"]).build_minutes == []  # redraw the report


def refused(argv: list[str], out: Path, capsys) -> str:
    """`elastreg bench ARGV --out OUT` on the shipped store: refused with exit status 2 before
    anything is made; its stderr."""
    with pytest.raises(SystemExit) as exit_:
        main(["bench", *argv, "--store", str(STORE), "--out", str(out), "--quick", "--no-fem"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and not out.exists(), err
    return err


@needs_liver()
@pytest.mark.parametrize(
    "argv, words",
    [
        # a ValueError traceback from own_sequences (rng.choice on no nodes near the paper's tool)
        (["liver", "--liver-model", "phantom"], "model 'phantom' cannot run the liver part"),
        (["pareto", "--liver-model", "phantom"], "model 'phantom' cannot run the pareto part"),
        (["stability", "--liver-model", "beam"], "model 'beam' cannot run the stability part"),
    ],
)
def test_a_liver_part_on_another_mesh_is_refused_before_any_work(argv, words, tmp_path, capsys):
    """The liver, pareto and stability parts run cases on the paper's liver, by its node ids: a
    model on another mesh was a traceback; now one line naming the model, the part and why."""
    err = refused(argv, tmp_path / "report", capsys)
    model = argv[-1]
    nodes = {"phantom": 1620, "beam": 500}[model]
    assert err == f"error: {words}: its mesh ({nodes} nodes) is not the paper's liver (3046 nodes)\n", err


def test_the_beam_part_on_a_model_without_a_free_end_is_refused_before_any_work(tmp_path, capsys):
    """`bench beam --beam-model phantom` made its cases, ran for minutes and ended in a traceback
    (the Newton method's Levenberg-Marquardt over 592 support nodes, 500 at most; tip loads of
    NaN, the phantom having one node at its largest x): both are said up front."""
    err = refused(["beam", "--beam-model", "phantom"], tmp_path / "report", capsys)
    assert err == (
        "error: model 'phantom' cannot run the beam part: its largest x is 1 node(s), not a free end for the tip "
        "loads (a face: 3 at least); its load region has 592 nodes, the Newton method's Levenberg-Marquardt rows "
        "take 500 at most\n"
    ), err


@needs_liver()
def test_a_liver_model_whose_region_misses_the_sequences_support_is_refused():
    """A model on the paper's liver needs the recorded sequence's support in its load region (the
    network refuses forces outside it): a narrowed region is named, the whole surface passes."""
    from service.bench.cases import liver_paper_mesh, liver_paper_support, not_on_paper_liver

    mesh, support = liver_paper_mesh(), liver_paper_support()
    assert not_on_paper_liver(mesh, mesh.free_surface_nodes) is None
    narrowed = np.setdiff1d(mesh.free_surface_nodes, support[:5])
    assert not_on_paper_liver(mesh, narrowed) == "its load region lacks 5 of the recorded sequence's support nodes"


def test_the_fem_part_without_the_papers_liver_is_refused_before_any_work(tmp_path, capsys, monkeypatch):
    """Without ../shared beside the checkout the fem part was a FileNotFoundError traceback."""
    from service.bench import cases

    monkeypatch.setattr(cases, "LIVER", tmp_path / "nowhere")
    err = refused(["fem"], tmp_path / "report", capsys)
    nowhere = tmp_path / "nowhere"
    assert (
        err
        == f"error: the fem part cannot run: the paper's liver is not in {nowhere} (../shared beside the checkout)\n"
    )


@pytest.mark.parametrize(
    "argv, line",
    [
        # each was exit status 1 (SystemExit with a message), the others' refusals being 2
        (["minutes", "--smoke", "bar"], "the minutes part builds scenes (--scenes), not a --smoke model"),
        (
            ["beam", "--beam-model", "nope"],
            "model 'nope' is not usable in {store} (nope: manifest.json is missing); "
            "build it with: elastreg train beam",
        ),
        (
            ["fem", "--smoke", "nope"],
            "model 'nope' is not usable in {store} (nope: manifest.json is missing); "
            "build it with: elastreg train SCENE",
        ),
        (
            ["minutes", "--scenes", "{tmp}/no.toml"],
            "{tmp}/no.toml: cannot read the scene file (No such file or directory) (the default scenes are relative "
            "to the repository's root)",
        ),
        # a scene's faults, one line each: one line in all
        (
            ["minutes", "--scenes", "{tmp}/empty.toml"],
            "{tmp}/empty.toml: name: missing (required); {tmp}/empty.toml: [mesh]: missing table; {tmp}/empty.toml: "
            "[material]: missing table; {tmp}/empty.toml: [training]: missing table (the default scenes are relative "
            "to the repository's root)",
        ),
    ],
)
def test_a_command_that_cannot_run_is_one_line_and_exit_status_2(argv, line, tmp_path, capsys):
    """A --smoke run of the minutes part, a missing model or an unreadable scene was exit status
    1 (or several lines): every refusal of the command line is one line, exit status 2, before
    any work."""
    (tmp_path / "empty.toml").write_text("")
    argv = [a.format(tmp=tmp_path) for a in argv]
    err = refused(argv, tmp_path / "report", capsys)
    assert err == "error: " + line.format(store=STORE, tmp=tmp_path) + "\n", err


def test_bad_settings_and_an_out_that_is_a_file_are_refused_before_any_work(tmp_path, capsys, monkeypatch):
    """An ELASTREG_* setting the server refuses was a pydantic traceback; an --out that is a file
    a FileExistsError traceback: both one line, exit status 2."""
    monkeypatch.setenv("ELASTREG_BLAS_THREADS", "many")
    err = refused(["beam"], tmp_path / "report", capsys)
    assert err.startswith("error: the ELASTREG_* settings: ELASTREG_BLAS_THREADS: ") and err.count("\n") == 1, err
    monkeypatch.delenv("ELASTREG_BLAS_THREADS")
    afile = tmp_path / "afile"
    afile.write_text("mine")
    with pytest.raises(SystemExit) as exit_:
        main(["bench", "beam", "--store", str(STORE), "--out", str(afile), "--quick", "--no-fem"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err == f"error: --out {afile} is not a folder a report can replace\n", err
    assert afile.read_text() == "mine"
    with pytest.raises(SystemExit) as exit_:  # the root: no name to swap a new folder in under
        main(["bench", "beam", "--store", str(STORE), "--out", "/", "--quick", "--no-fem"])
    assert exit_.value.code == 2 and capsys.readouterr().err == "error: --out / is not a folder a report can replace\n"


def test_the_pareto_parts_variants_are_checked_before_any_work(tmp_path, capsys):
    """The pareto part also scores every model of the store named LIVERMODEL_*, found only when
    it ran (minutes in): one it could not load was left out with a logged line, one on another
    mesh a traceback. Each is now loaded and checked with the part's own model, before any
    work: one line naming it, exit status 2."""
    from service.store.files import WEIGHTS

    store, out = tmp_path / "store", tmp_path / "report"
    shutil.copytree(STORE / "phantom", store / "phantom")
    shutil.copytree(STORE / "phantom", store / "phantom_small")  # a copy under another name
    argv = ["bench", "pareto", "--liver-model", "phantom", "--store", str(store), "--out", str(out), "--quick"]
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and not out.exists(), err
    assert err == (
        "error: model 'phantom_small', a variant the pareto part scores, says it is 'phantom' (rename or remove "
        "the folder)\n"
    ), err
    shutil.rmtree(store / "phantom_small")
    shutil.copytree(STORE / "phantom", store / "phantom_broken")
    (store / "phantom_broken" / WEIGHTS).write_bytes(b"cut short")
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and not out.exists(), err
    assert err == (
        f"error: model 'phantom_broken' is not usable in {store} (phantom_broken: {WEIGHTS} does not match its "
        "checksum in the manifest (corrupt or changed)); build it with: elastreg train "
        "benchmarks/scenes/liver_paper.toml --name ID ... (docs/usage.md's recipe), or remove the folder from the "
        "store\n"
    ), err


def bench_parser() -> argparse.ArgumentParser:
    sub = next(a for a in parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices["bench"]


def test_every_bench_flag_with_a_default_says_it_in_its_help():
    """`bench --help` gave --liver-model and --beam-model no help at all, and --sites, --truth,
    --test-paths and --workers no default: each flag that has one says it."""
    quiet = [a for a in bench_parser()._actions if a.default not in (None, False, argparse.SUPPRESS)]
    assert {a.dest for a in quiet} >= {"liver_model", "beam_model", "sites", "truth", "test_paths", "workers"}
    for action in quiet:
        assert action.help and "default" in action.help, action.option_strings or action.dest


def test_the_bench_lines_of_usage_md_name_real_flags_and_their_defaults():
    """docs/usage.md's `elastreg bench` lines show a bracketed flag with its default: `bench
    minutes [--out reports/build-minutes]` read as the minutes part's default folder, where the
    code's is reports/latest for every part. Every flag shown is one of the command's, and a
    bracketed value is its default."""
    usage = (Path(__file__).resolve().parents[2] / "docs" / "usage.md").read_text()
    lines = [line for line in usage.splitlines() if line.startswith("elastreg bench")]
    actions = {s: a for a in bench_parser()._actions for s in a.option_strings}
    assert len(lines) >= 2
    for line in lines:
        for flag in re.findall(r"--[\w-]+", line):
            assert flag in actions, (flag, line)
        for flag, shown in re.findall(r"\[(--[\w-]+)([^\]]*)\]", line):
            values = shown.split()
            if not values or any(v == "..." or v.isupper() or v.endswith(".toml") for v in values):
                continue  # a switch, or a placeholder
            action = actions[flag]
            parsed = [action.type(v) if action.type else v for v in values]
            assert (parsed if action.nargs else parsed[0]) == action.default, (flag, line)


def test_a_missing_liver_model_points_at_the_recipe_in_usage_md(tmp_path, capsys):
    """The hint said "(see the README)", which has no liver recipe: docs/usage.md's section has."""
    with pytest.raises(SystemExit) as exit_:
        main(["bench", "liver", "--store", str(tmp_path), "--out", str(tmp_path / "report"), "--quick", "--no-fem"])
    message = capsys.readouterr().err
    assert exit_.value.code == 2
    assert "elastreg train benchmarks/scenes/liver_paper.toml" in message and "README" not in message, message
    section = re.search(r'docs/usage\.md, "([^"]+)"', message)
    usage = (Path(__file__).resolve().parents[2] / "docs" / "usage.md").read_text()
    assert section and f"\n## {section[1]}" in usage, message


@pytest.mark.parametrize(
    "prior, why",
    [
        ({"parts": {"anysite": {"summaries": []}}}, "its anysite part cannot be drawn (KeyError: 'model')"),
        ({"parts": {"liver": {"records": [{"case": "x"}], "summaries": []}}}, "it cannot be merged (TypeError: "),
        ({"parts": ["beam"]}, "its parts are not a mapping of part names to their results"),
        ({"machine": [], "parts": {"pareto": []}}, "it cannot be merged (AttributeError: "),
    ],
)
def test_a_report_of_the_wrong_shape_in_out_is_refused_before_any_work(prior, why, bar_store, tmp_path, capsys):
    """A results.json in --out that is JSON of the wrong shape was read only after every part had
    run: a traceback in the merge or the report, the new report lost. Each part the run would
    keep is now merged and drawn before any work: one line, exit status 2, nothing changed."""
    out = tmp_path / "report"
    out.mkdir()
    (out / "results.json").write_text(json.dumps({"smoke": "bar", **prior}))
    with pytest.raises(SystemExit) as exit_:
        main(["bench", "fem", "--smoke", "bar", "--store", str(bar_store[0]), "--out", str(out)])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith(f"error: {out / 'results.json'} is not a report this run can keep: {why}"), err
    assert err.endswith("; give another --out, or --replace to replace it\n"), err
    assert sorted(p.name for p in out.iterdir()) == ["results.json"] and not list(tmp_path.glob(".bench-*"))
    assert main(["bench", "fem", "--smoke", "bar", "--store", str(bar_store[0]), "--out", str(out), "--replace"]) == 0


def test_the_anysite_heading_says_how_many_sites_the_build_held_out():
    """With one of six sites held out the heading said "sites and loads held out"; it says how
    many now, and a build that held none out keeps its words (loads and truth held out, not sites)."""
    from service.bench.markdown import held_out_words

    assert held_out_words(6, 6)[0] == "sites and loads"
    heading, body = held_out_words(1, 6)
    assert heading == "1 of 6 sites, and loads," and "1 of the 6 sites held out of the build" in body
    heading, body = held_out_words(0, 6)
    assert heading == "loads" and "not the sites" in body

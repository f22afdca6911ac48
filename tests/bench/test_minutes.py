"""The build-minutes part: real timed builds of a small scene, scored on one held-out test set."""

import json

import numpy as np
import pytest
import torch

from service.bench.machine import cores
from service.bench.minutes import TEST_SEED, latest, merge, timed_build
from service.bench.minutes import test_set as solve_test_set  # not "test_*" here: pytest would collect it
from service.cli import main
from service.network_size import FEATURES, WEIGHT_DECAY
from service.scene import load_scene
from service.store import load_entry
from service.surrogate.train import TrainConfig
from tests.conftest import write_bar_scene


def test_minutes_part_builds_on_the_clock_and_keeps_its_rows(bar, tmp_path):
    scene = write_bar_scene(tmp_path / "scene", bar)
    out = tmp_path / "report"
    common = ["bench", "minutes", "--scenes", str(scene), "--test-data", str(tmp_path / "test"), "--out", str(out)]
    kept = tmp_path / "kept"
    assert (
        main([*common, "--build-minutes", "0.2", "--test-paths", "3", "--workers", "0", "--keep-store", str(kept)]) == 0
    )
    entry = load_entry(kept / "bar")  # kept for the other parts, and verified on loading
    assert entry.manifest["training"]["minutes"] == 0.2
    (row,) = json.loads((out / "results.json").read_text())["parts"]["minutes"]["rows"]
    assert row["scene"] == "bar" and row["minutes"] == 0.2 and row["test_seed"] == TEST_SEED
    assert row["wall_s"] <= 0.2 * 60 + 10  # the whole build on the clock (scoring is outside it)
    # trained on a thread a core, as `elastreg train` does, and the bench's one thread back after
    assert row["train_threads"] == cores() and torch.get_num_threads() == 1
    assert (row["features"], row["weight_decay"]) == (FEATURES, WEIGHT_DECAY)  # the defaults, recorded
    assert row["test_samples"] > 0 and row["samples"] > 0
    assert len(row["test_loads"]) == 12  # the test set's identity: its loads' hash
    # the build is never worse than linear physics on its own paths, and both beat no deformation
    assert 0 < row["test_relative"] < 1 and 0 < row["test_linear_relative"] < 1
    assert row["test_relative_median"] <= row["test_relative"] * 3
    assert row["test_mean_mm"] < row["test_zero_mean_mm"]
    # no budgets: the report is redrawn from the rows kept, none lost
    assert main([*common, "--build-minutes"]) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["parts"]["minutes"]["rows"] == [row]
    report = (out / "report.md").read_text()
    assert "Validation error against build minutes" in report and "| bar | 0.2 |" in report
    assert (out / "figures" / "build_minutes.png").stat().st_size > 1000
    assert json.loads((out / "minutes_rows.json").read_text()) == [row]


def test_a_rerun_replaces_its_commits_row_and_keeps_history():
    def row(commit, started, rel):
        return {"scene": "s", "minutes": 10.0, "layout": "physics", "commit": commit, "started": started,
                "test_relative": rel}  # fmt: skip

    rows = merge([row("a", "1", 0.3), row("b", "2", 0.2)], row("b", "3", 0.1))
    assert [r["commit"] for r in rows] == ["a", "b"] and rows[-1]["test_relative"] == 0.1
    assert latest(rows) == [rows[-1]]  # the newest row of a scene and budget
    assert latest([{**row("c", "4", 0.1), "layout": "raw"}]) == []  # other layouts are history only


def test_minutes_part_refuses_a_smoke_model_and_a_missing_scene(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["bench", "minutes", "--smoke", "bar", "--out", str(tmp_path)])
    assert exit_.value.code == 2 and "minutes part builds scenes" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:
        main(["bench", "minutes", "--scenes", str(tmp_path / "nowhere.toml"), "--out", str(tmp_path / "r")])
    assert exit_.value.code == 2 and "cannot read the scene file" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()  # nothing made for a bad command, not even the folder


def test_a_stopped_runs_rows_are_merged_back_by_resume(bar, tmp_path, capsys):
    """The rows a stopped `bench minutes` set aside (NAME.interrupted-TIME) could not be fed back
    into a report: a user copied them by hand. Now --resume merges them, when built on this
    machine at this commit (else refused: one line, exit status 2, nothing written), and the
    budgets they hold are not built again."""
    from service.bench import machine

    here = machine.describe()
    scene = write_bar_scene(tmp_path / "scene", bar)
    out = tmp_path / "report"
    old = {"scene": "bar", "minutes": 30.0, "layout": "physics", "commit": "0ld", "cpu": "elsewhere",
           "started": "2026-11-01 10:00:00", "test_relative": 0.3, "test_linear_relative": 0.5}  # fmt: skip
    (out / "figures").mkdir(parents=True)
    (out / "results.json").write_text(json.dumps({"smoke": None, "parts": {"minutes": {"rows": [old]}}}))
    built = {**old, "minutes": 0.2, "commit": here["commit"], "cpu": here["cpu"], "started": "2026-12-01 10:00:00",
             "test_relative": 0.2}  # fmt: skip
    aside = tmp_path / "report.interrupted-20261201-100000"
    aside.mkdir()
    (aside / "minutes_rows.json").write_text(json.dumps([old, built]))  # the old report's rows, and its own
    elsewhere = tmp_path / "other.interrupted-20261201-100000"
    elsewhere.mkdir()
    (elsewhere / "minutes_rows.json").write_text(json.dumps([old, {**built, "commit": "0ther"}]))
    before = (out / "results.json").read_bytes()

    argv = ["bench", "minutes", "--scenes", str(scene), "--test-data", str(tmp_path / "test"), "--out", str(out),
            "--build-minutes", "0.2", "--test-paths", "2", "--workers", "0"]  # fmt: skip
    with pytest.raises(SystemExit) as exit_:
        main([*argv, "--resume", str(elsewhere)])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1, err
    assert err.startswith(f"error: --resume {elsewhere}: its row for bar at 0.2 minutes was built at commit 0ther"), err
    assert (out / "results.json").read_bytes() == before and sorted(p.name for p in out.iterdir()) == [
        "figures",
        "results.json",
    ]

    assert main([*argv, "--resume", str(aside / "minutes_rows.json")]) == 0
    rows = json.loads((out / "results.json").read_text())["parts"]["minutes"]["rows"]
    assert rows == [old, built]  # the budget the stopped run built is not built again
    assert not (tmp_path / "test").exists()  # nor its scene's test set solved
    assert "| bar | 0.2 |" in (out / "report.md").read_text()
    assert json.loads((aside / "minutes_rows.json").read_text()) == [old, built]  # kept for the user to remove


def test_scenes_that_parse_but_cannot_be_built_are_refused_in_one_line_before_any_work(bar, tmp_path, capsys):
    """Before: a scene whose fixed_box selects no node, or whose mesh is tangled, parsed, and the
    run failed in its first build with a SceneError traceback, exit status 1, the --out folder
    made. Now every scene is checked whole first: all their faults in one line, exit status 2,
    nothing written."""
    import meshio

    from service.phantoms import grid_tets

    clamp = write_bar_scene(tmp_path / "clamp", bar)
    clamp.write_text(clamp.read_text().replace("[[-0.01, -1, -1], [0.01, 2, 2]]", "[[5, 5, 5], [6, 6, 6]]"))
    tangled = write_bar_scene(tmp_path / "tangled", bar, name="tangled")
    nodes, tets = grid_tets((3, 3, 3), 1.0 / 3.0)
    inner = int(np.flatnonzero((np.abs(nodes - 0.5) < 0.2).all(axis=1))[0])
    t = int(np.flatnonzero((tets == inner).any(axis=1))[0])
    face = nodes[tets[t][tets[t] != inner]].mean(axis=0)
    nodes[inner] = face + 1.5 * (face - nodes[inner])  # through the opposite face (tests/test_mesh.py)
    meshio.write(tangled.parent / "bar.vtu", meshio.Mesh(nodes, [("tetra", tets)]))
    out = tmp_path / "report"
    with pytest.raises(SystemExit) as exit_:
        main(["bench", "minutes", "--scenes", str(clamp), str(tangled), "--test-data", str(tmp_path / "test"),
              "--out", str(out), "--build-minutes", "0.2", "--workers", "0"])  # fmt: skip
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1, err
    assert f"{clamp}: [boundary] fixed_box: " in err and f"{tangled}: [mesh] path: " in err and "is tangled" in err
    assert not out.exists() and not (tmp_path / "test").exists()


def test_a_kept_builds_rebuild_command_names_a_scene_train_takes(bar, tmp_path, monkeypatch):
    """It said `elastreg train NAME.toml`: a file seldom in the folder the command is run from."""
    import os

    from service.bench.minutes import scene_argument
    from service.scene import builtin_scene, load_scene

    assert scene_argument(builtin_scene("beam")) == "beam"
    path = write_bar_scene(tmp_path / "scenes", bar, samples=6)
    monkeypatch.chdir(tmp_path)
    assert scene_argument(load_scene(path.relative_to(tmp_path))) == os.path.realpath(path)


@pytest.mark.parametrize("minutes", [float("nan"), -5.0, 0, True, "10"])
def test_resumed_rows_with_an_impossible_budget_are_refused(minutes, tmp_path, capsys):
    """--resume took a row whose minutes were NaN, negative or a bool and crashed in the plot
    (a traceback after the merge): such a row is refused, one line, exit status 2."""
    from service.bench import machine

    here = machine.describe()
    aside = tmp_path / "report.interrupted-20261201-100000"
    aside.mkdir()
    row = {"scene": "bar", "minutes": minutes, "layout": "physics", "commit": here["commit"], "cpu": here["cpu"],
           "started": "2026-12-01 10:00:00", "test_relative": 0.2, "test_linear_relative": 0.5}  # fmt: skip
    (aside / "minutes_rows.json").write_text(json.dumps([row]))
    out = tmp_path / "report"
    with pytest.raises(SystemExit) as exit_:
        main(["bench", "minutes", "--resume", str(aside), "--build-minutes", "--out", str(out)])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert f"holds no minutes part's rows: its row for bar has minutes {minutes!r}, not a positive finite" in err
    assert not out.exists()


def test_a_redraw_with_no_rows_is_refused(tmp_path, capsys):
    """`bench minutes --build-minutes` (no budgets: redraw from the rows kept) into a folder with
    no rows wrote an empty report and exit status 0: now one line, exit status 2, nothing made."""
    out = tmp_path / "report"
    with pytest.raises(SystemExit) as exit_:
        main(["bench", "minutes", "--build-minutes", "--out", str(out)])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err == (
        f"error: --build-minutes with no values redraws the report from its rows, and {out} holds none (nor "
        "--resume): name the budgets to build\n"
    ), err
    assert not out.exists()


def test_a_curve_holds_one_machine_and_one_test_set(tmp_path):
    """latest() took the newest row of each budget whatever its machine or test set (the
    committed curve's liver_deepphysx rows had 177 and 175 test samples), under a report that
    says "the same loads for every budget": now a scene's curve holds the rows of its newest
    row's machine and test set, the others listed apart in the report."""
    from service.bench.markdown import write_report
    from service.bench.minutes import left_out

    def row(minutes, started, cpu="A", loads="aaaa", samples=177):
        return {"scene": "s", "minutes": minutes, "layout": "physics", "commit": "c", "started": started, "cpu": cpu,
                "test_samples": samples, "test_loads": loads, "test_relative": 0.1}  # fmt: skip

    rows = [row(5.0, "1"), row(10.0, "2", samples=175, loads="bbbb"), row(30.0, "3", cpu="B"), row(60.0, "4")]
    assert [r["minutes"] for r in latest(rows)] == [5.0, 60.0]
    assert [r["minutes"] for r in left_out(rows)] == [10.0, 30.0]
    out = tmp_path / "report"
    (out / "figures").mkdir(parents=True)
    machine = dict.fromkeys(("cpu", "cores", "gpu", "commit", "sparse_solver", "torch", "numpy", "scipy"), "-")
    write_report({"started": "-", "seconds": 0.0, "machine": machine, "parts": {"minutes": {"rows": rows}}}, out)
    report = (out / "report.md").read_text()
    assert "| s | 5 |" in report and "| s | 60 |" in report and "| s | 10 |" not in report
    assert "177, aaaa |" in report
    assert "s at 10 minutes (A, test set 175, bbbb); s at 30 minutes (B, test set 177, aaaa)." in report


def test_a_timed_build_of_other_settings_is_built_and_recorded_as_asked(bar, tmp_path):
    """timed_build with a config and a thread count (benchmarks/settings_build.py's): the entry
    is trained with those settings on those threads, its rebuild command names them, and the row
    says so; the bench's one thread is back after."""
    scene = load_scene(write_bar_scene(tmp_path / "scene", bar))
    config = TrainConfig(physics_skip=True, features=4, weight_decay=1e-3)
    test = solve_test_set(scene, 3, tmp_path / "test", 0)
    torch.set_num_threads(1)
    row = timed_build(scene, 0.1, test, workers=0, keep=tmp_path / "kept", config=config, threads=2)
    assert (row["features"], row["weight_decay"], row["train_threads"]) == (4, 1e-3, 2)
    assert torch.get_num_threads() == 1
    manifest = load_entry(tmp_path / "kept" / "bar").manifest
    assert manifest["training"]["config"]["features"] == 4 and manifest["training"]["config"]["weight_decay"] == 1e-3
    assert manifest["rebuild"].endswith("--minutes 0.1 --features 4 --weight-decay 0.001")
    assert 0 < row["test_relative"] < 1

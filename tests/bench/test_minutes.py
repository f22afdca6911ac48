"""The build-minutes part: real timed builds of a small scene, scored on one held-out test set."""

import json

import pytest

from service.bench.minutes import TEST_SEED, latest, merge
from service.cli import main
from service.store import load_entry
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
    assert row["test_samples"] > 0 and row["samples"] > 0
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

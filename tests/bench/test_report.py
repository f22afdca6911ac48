"""`elastreg bench`'s flags: an impossible value is one line naming the flag and exit status 2
at parse time, before the report folder, a test set or a build is touched."""

import pytest

from service.cli import main, parser


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

"""The report folder's swap: a run stopped at any instant leaves `--out` the old report or the
new one, whole, and the next run clears what it left."""

import fcntl
import json
import os
import stat
import sys
from pathlib import Path

import pytest

from service.bench import swap
from service.cli import main
from tests.bench.test_smoke import files


def smoke(store: Path, out: Path, *more: str) -> list[str]:
    """The cheapest real run: the fem part of a --smoke run on the bar."""
    return ["bench", "fem", "--smoke", "bar", "--store", str(store), "--out", str(out), *more]


def tree(fd: int) -> dict[str, bytes]:
    """Every file under the folder open as `fd` (one folder, whatever is renamed meanwhile), the
    scratch folders of versions that wrote theirs inside the report left out."""
    found = {}
    for name in os.listdir(fd):
        if name.startswith(".bench-"):
            continue
        if stat.S_ISDIR(os.stat(name, dir_fd=fd, follow_symlinks=False).st_mode):
            sub = os.open(name, os.O_RDONLY | os.O_DIRECTORY, dir_fd=fd)
            try:
                found.update({f"{name}/{k}": v for k, v in tree(sub).items()})
            finally:
                os.close(sub)
        else:
            f = os.open(name, os.O_RDONLY, dir_fd=fd)
            with open(f, "rb") as r:
                found[name] = r.read()
    return found


def snapshot(folder: Path) -> dict[str, bytes] | None:
    """What a reader opening `folder` now finds: its files, or None where there is no folder."""
    try:
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    except FileNotFoundError:
        return None
    try:
        return tree(fd)
    finally:
        os.close(fd)


#: the file-system steps before each of which a reader's view of the report is taken
STEPS = {"os.rename", "os.link", "os.remove", "shutil.rmtree", "ctypes.call_function"}
_watch: list = []  # [out, views]: the audit hook's target while a test runs; hooks stay for good


def _hook(event: str, _args) -> None:
    if _watch and event in STEPS:
        out, views = _watch.pop()
        try:
            views.append((snapshot(out), snapshot(swap.backup_of(out))))
        finally:
            _watch.append((out, views))


sys.addaudithook(_hook)


@pytest.mark.parametrize("exchange", [True, False], ids=["one exchange", "two renames"])
def test_the_report_is_never_seen_half_written(bar_store, tmp_path, capsys, monkeypatch, exchange):
    """The run moved its files into `--out` one at a time: a run stopped between two moves left
    new files beside old ones. Before each file-system step of a run's ending, the folder a
    reader opens is the old report or the new one, whole (between the two renames of a file
    system without an exchange: no folder, the old one whole beside it, which the next run puts
    back)."""
    if not exchange:  # a system or file system without renameat2's exchange
        monkeypatch.setattr(swap, "_renameat2", None)
    out = tmp_path / "report"
    assert main(smoke(bar_store[0], out)) == 0
    (out / "mine.txt").write_text("a file of the user's, kept by a run that merges")
    out.chmod(0o750)  # the folder's own permissions, kept (not the scratch folder's 0700)
    old = snapshot(out)
    views: list = []
    _watch.append((out, views))
    try:
        assert main(smoke(bar_store[0], out)) == 0
    finally:
        _watch.clear()
    new = snapshot(out)
    assert new is not None and new != old and new["mine.txt"] == old["mine.txt"]
    seen = [view for view, _ in views]
    assert old in seen and new in seen, [sorted(v or {}) for v in seen]
    for view, backup in views:
        assert view in (old, new) or (view is None and backup == old and not exchange), sorted(view or {})
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".bench-")]
    assert stat.S_IMODE(out.stat().st_mode) == 0o750


def leftover(out: Path, name: str) -> Path:
    """A scratch folder as a run killed while writing it leaves one: half its files."""
    path = out.parent / name
    (path / "figures").mkdir(parents=True)
    (path / "results.json").write_text('{"parts": {"fe')
    return path


def test_a_run_killed_between_the_two_renames_is_undone_by_the_next(bar_store, tmp_path, capsys):
    """A run killed (SIGKILL) after putting the old report aside and before putting its own in
    place leaves no `--out`, the old report as .bench-NAME.old and its scratch folder: the next
    run put its report in a new folder, the old one lost. Now the old report is put back, the
    scratch removed, one line each, and the run merges with the report as it was."""
    out = tmp_path / "report"
    assert main(smoke(bar_store[0], out)) == 0
    (out / "mine.txt").write_text("kept")
    os.rename(out, swap.backup_of(out))
    scratch = leftover(out, ".bench-report-k1ll3d_x")
    capsys.readouterr()
    assert main(smoke(bar_store[0], out)) == 0
    err = capsys.readouterr().err.splitlines()
    assert f"note: removed {scratch}, the scratch folder of a run stopped before its report went in" in err, err
    backup = swap.backup_of(out)
    assert f"note: restored {out} from {backup}, where a run stopped while swapping reports had put it" in err, err
    assert (out / "mine.txt").read_text() == "kept" and "fem" in json.loads((out / "results.json").read_text())["parts"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]


def test_a_run_killed_after_the_second_rename_leaves_its_report(bar_store, tmp_path, capsys):
    """Killed once its report was in place, before the old one was removed: the old report
    under .bench-NAME.old is removed by the next run, with one line, the report in place kept."""
    out = tmp_path / "report"
    assert main(smoke(bar_store[0], out)) == 0
    backup = swap.backup_of(out)
    backup.mkdir()
    (backup / "results.json").write_text("{}")
    capsys.readouterr()
    assert main(smoke(bar_store[0], out)) == 0
    err = capsys.readouterr().err.splitlines()
    assert f"note: removed {backup}, the old report of a run stopped once its own was in {out}" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]


def test_an_older_versions_scratch_inside_the_report_is_removed(bar_store, tmp_path, capsys):
    """Versions before wrote their scratch folder inside `--out` (.bench-XXXXXXXX): one that a
    SIGKILL left stayed there for good. The next run removes it, with one line."""
    out = tmp_path / "report"
    out.mkdir()
    stray = leftover(out / "x", ".bench-abcd1234").rename(out / ".bench-abcd1234")
    capsys.readouterr()
    assert main(smoke(bar_store[0], out)) == 0
    err = capsys.readouterr().err.splitlines()
    assert f"note: removed {stray}, the scratch folder of a run stopped before its files were moved" in err, err
    assert not list(out.glob(".bench-*")) and (out / "report.md").exists()


def test_a_run_into_a_folder_another_run_is_writing_is_refused(bar_store, tmp_path, capsys):
    """A live run's scratch folder (locked as long as its process lives) is not a leftover: a
    second run into the same `--out` is refused, one line, exit status 2, nothing touched."""
    out = tmp_path / "report"
    scratch = leftover(out, ".bench-report-l1v3run_")
    before = files(scratch)
    fd = os.open(scratch, os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(SystemExit) as exit_:
            main(smoke(bar_store[0], out))
    finally:
        os.close(fd)
    err = capsys.readouterr().err
    assert exit_.value.code == 2
    assert err == f"error: another elastreg bench is writing {out} (its scratch folder {scratch} is locked)\n", err
    assert files(scratch) == before and not out.exists()

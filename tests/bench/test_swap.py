"""The report folder's swap: a run stopped at any instant leaves `--out` the old report or the
new one, whole, and the next run clears what it left."""

import fcntl
import json
import os
import re
import shlex
import shutil
import stat
import subprocess
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
        monkeypatch.setattr(swap, "exchange", lambda a, b: False)
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


@pytest.mark.parametrize("parent", ["writable", "not writable"])
def test_rows_left_in_a_scratch_inside_the_report_are_set_aside_or_kept(tmp_path, parent):
    """A run that could not swap (its scratch inside --out) and was killed after a build: its
    rows were removed with the folder by the next run. Now they go beside --out like a swapped
    run's, or, where nothing can be made beside it (a parent the user cannot write), stay in
    place, which no run removes; one line each way."""
    www = tmp_path / "www"
    out = www / "report"
    scratch = leftover(out / "x", ".bench-abcd1234").rename(out / ".bench-abcd1234")
    (scratch / "minutes_rows.json").write_text('[{"minutes": 0.1}]')
    line = "import sys; from pathlib import Path; from service.bench.swap import recover; " \
        "print(*recover(Path(sys.argv[1])))"  # fmt: skip
    drop: list[str] = []
    if parent == "not writable" and os.geteuid() == 0:
        if not shutil.which("setpriv"):
            pytest.skip("root without setpriv: every folder is writable")
        os.chown(www, 65534, -1)  # nobody's: without CAP_DAC_OVERRIDE/FOWNER, root cannot write it
        tmp_path.chmod(0o755)
        drop = ["setpriv", "--inh-caps=-all", "--bounding-set=-dac_override,-dac_read_search,-fowner", "--"]
    if parent == "not writable":
        www.chmod(0o555)
    done = subprocess.run([*drop, sys.executable, "-c", line, str(out)], capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    if parent == "writable":
        (aside,) = www.glob("report.interrupted-*")
        assert done.stdout == f"moved {scratch}, a run stopped before its files were moved, to {aside}: its " \
            "minutes_rows.json holds the rows built so far\n", done.stdout  # fmt: skip
    else:
        aside = scratch
        assert done.stdout.startswith(f"kept {scratch}, a run stopped before its files were moved, for its minutes "
                                      f"rows (not moved beside {out}: Permission denied"), done.stdout  # fmt: skip
    assert json.loads((aside / "minutes_rows.json").read_text()) == [{"minutes": 0.1}]


#: `elastreg` run in a process of its own
CLI = "import sys; from service.cli import main; sys.exit(main(sys.argv[1:]))"
ROOT = Path(__file__).resolve().parents[2]


#: `elastreg ARGV` in a process of its own that, at the first audit event EVENT whose path
#: matches PATTERN, makes the file READY and waits until the file GO exists
PAUSED = """import fnmatch, os, sys, time
event_, pattern, ready, go = sys.argv[1:5]
def pause(event, args):
    if event == event_ and isinstance(args[0], str) and fnmatch.fnmatch(args[0], pattern) and not os.path.exists(ready):
        open(ready, "w").close()
        while not os.path.exists(go):
            time.sleep(0.02)
sys.addaudithook(pause)
from service.cli import main
sys.exit(main(sys.argv[5:]))
"""


def paused(event: str, pattern: str, ready: Path, go: Path, argv: list[str]) -> subprocess.Popen:
    """`elastreg ARGV` started, to pause at EVENT on PATTERN (:data:`PAUSED`)."""
    return subprocess.Popen([sys.executable, "-c", PAUSED, event, pattern, str(ready), str(go), *argv], cwd=ROOT,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip


def wait_for(proc: subprocess.Popen, ready: Path) -> None:
    """Until `proc` has made `ready` (it pauses there) or has ended."""
    import time

    deadline = time.monotonic() + 120
    while not ready.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)


def test_two_runs_into_one_folder_at_once_keep_both_parts_or_refuse_one(bar_store, tmp_path):
    """A second run into --out was refused only once the first had made its scratch folder: one
    started before that (while the first loaded its models) read the same old report, and the
    one that swapped in last dropped the other's part, its files linked in beside a results.json
    without it (a mixed report), though both said 'report written'. Now a run holds a lock beside
    --out from the start, and the second is refused: one line, exit status 2."""
    out = tmp_path / "report"
    first_argv = smoke(bar_store[0], out)
    second_argv = ["bench", "beam", *first_argv[2:]]
    first = paused("os.mkdir", str(out), tmp_path / "ready1", tmp_path / "go1", first_argv)
    second = None
    try:
        wait_for(first, tmp_path / "ready1")  # the first has read --out and is about to make it
        # the second pauses (if it runs at all) as it writes its report, its merge with --out done
        second = paused("open", f"{tmp_path}/.bench-report-*/report.md", tmp_path / "ready2", tmp_path / "go2",
                        second_argv)  # fmt: skip
        wait_for(second, tmp_path / "ready2")
        (tmp_path / "go1").touch()
        _, err1 = first.communicate(timeout=120)
        (tmp_path / "go2").touch()
        _, err2 = second.communicate(timeout=120)
    finally:
        for proc in (first, second):
            if proc is not None:
                proc.kill()
                proc.wait()
    assert first.returncode == 0, err1
    parts = set(json.loads((out / "results.json").read_text())["parts"])
    for proc, part in ((first, "fem"), (second, "beam")):
        assert proc.returncode != 0 or part in parts, (part, parts)  # a run that says its report is written
    lock = tmp_path / ".bench-report.lock"
    assert second.returncode == 2 and err2 == f"error: another elastreg bench is writing {out} (it holds {lock})\n", (
        err2
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["go1", "go2", "ready1", "report"]


def in_own_mounts(mounts: str, argv: list[str], after: str = "true") -> subprocess.CompletedProcess:
    """`elastreg ARGV` in a mount namespace of its own between the shell lines `mounts` and
    `after` (its exit status kept), or a skip where mounts cannot be made here."""
    if os.geteuid() != 0 or not shutil.which("unshare"):
        pytest.skip("needs root and unshare to make mounts")
    probe = subprocess.run(["unshare", "-m", "--propagation", "private", "true"], capture_output=True, text=True)
    if probe.returncode:
        pytest.skip(f"cannot unshare the mount namespace: {probe.stderr.strip()}")
    run = f"{shlex.quote(sys.executable)} -c {shlex.quote(CLI)} {shlex.join(argv)}"
    script = f"{mounts} || exit 99; {run}; rc=$?; {after}; exit $rc"
    return subprocess.run(["unshare", "-m", "--propagation", "private", "sh", "-c", script], capture_output=True,
                          text=True, cwd=ROOT)  # fmt: skip


def test_a_mount_point_out_gets_its_files_moved_in(bar_store, tmp_path):
    """--out a mount point (a bind mount, a docker volume): the exchange failed with EBUSY and
    the finished report was deleted (traceback, exit 1). Now its files are moved in one by one,
    with one note, the user's file kept."""
    out, volume = tmp_path / "report", tmp_path / "volume"
    out.mkdir()
    volume.mkdir()
    (volume / "mine.txt").write_text("kept")
    done = in_own_mounts(f"mount --bind {volume} {out}", smoke(bar_store[0], out))
    assert done.returncode == 0, done.stderr
    assert "note: could not swap the report into" in done.stderr and "moved in one by one" in done.stderr, done.stderr
    assert (volume / "mine.txt").read_text() == "kept"
    assert "fem" in json.loads((volume / "results.json").read_text())["parts"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report", "volume"]
    assert not list(volume.glob(".bench-*"))


def test_an_overlayfs_lower_layer_out_gets_its_files_moved_in(bar_store, tmp_path):
    """--out a folder of an overlay's lower layer (a container image's reports/latest): EXDEV
    from the exchange and the renames, the report deleted. Now moved in one by one."""
    root = tmp_path / "ov"
    lower = root / "lower/reports/latest"
    lower.mkdir(parents=True)
    (lower / "report.md").write_text("the image's report")
    out = root / "merged/reports/latest"
    mounts = (f"mount -t tmpfs tmpfs {root / 'up'} 2>/dev/null || true; mkdir -p {root}/up/u {root}/up/w; "
              f"mount -t overlay overlay -o lowerdir={root}/lower,upperdir={root}/up/u,workdir={root}/up/w "
              f"{root}/merged")  # fmt: skip
    (root / "up").mkdir()
    (root / "merged").mkdir()
    after = f"echo beside: $(ls -A {out.parent}); grep -q FEM {out}/report.md && echo the new report"
    done = in_own_mounts(mounts, smoke(bar_store[0], out, "--replace"), after)
    if done.returncode == 99:
        pytest.skip(f"cannot mount an overlay here: {done.stderr.strip()}")
    assert done.returncode == 0, done.stderr
    assert "note: could not swap the report into" in done.stderr, done.stderr
    assert "beside: latest\nthe new report\n" in done.stdout, done.stdout


def test_an_out_in_a_parent_the_user_cannot_write_is_written(bar_store, tmp_path, capsys):
    """--out writable inside a parent that is not (a served folder /srv/www/report): the scratch
    folder beside it could not be made, a PermissionError traceback. Now it is made inside."""
    if os.geteuid() == 0 and not shutil.which("setpriv"):
        pytest.skip("root without setpriv: every folder is writable")
    www = tmp_path / "www"
    out = www / "report"
    out.mkdir(parents=True)
    (out / "mine.txt").write_text("kept")
    os.chown(www, 65534, -1)  # nobody's: without CAP_DAC_OVERRIDE/FOWNER, root cannot write it
    www.chmod(0o755)
    tmp_path.chmod(0o755)
    drop = ["setpriv", "--inh-caps=-all", "--bounding-set=-dac_override,-dac_read_search,-fowner", "--"]
    done = subprocess.run([*drop, sys.executable, "-c", CLI, *smoke(bar_store[0], out)], capture_output=True,
                          text=True, cwd=ROOT)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "so the report's files are moved into it one by one" in done.stderr, done.stderr
    assert (out / "mine.txt").read_text() == "kept" and (out / "report.md").exists()
    assert not list(out.glob(".bench-*")) and sorted(p.name for p in www.iterdir()) == ["report"]


def test_out_dot_keeps_the_callers_working_directory(bar_store, tmp_path, capsys, monkeypatch):
    """`--out .` from the report folder: the swap left the caller's shell in the old, deleted
    folder. Now the files are moved into the folder the caller stands in."""
    out = tmp_path / "report"
    out.mkdir()
    (out / "mine.txt").write_text("kept")
    monkeypatch.chdir(out)
    assert main(smoke(bar_store[0], Path("."))) == 0
    here = os.listdir(".")
    assert "report.md" in here and "mine.txt" in here and not [n for n in here if n.startswith(".bench-")], here
    assert os.path.samefile(".", out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]


def test_a_finished_report_that_cannot_go_in_is_kept_from_the_next_run(bar_store, tmp_path, capsys, monkeypatch):
    """A finished report whose files could not be moved in (here a folder of the user's named
    report.md) stayed in its scratch folder, named by one error line, exit status 1; the next run
    into that --out removed it as a stopped run's leftover. Now it is set aside beside --out as
    NAME.unplaced-TIME, which no run clears."""
    out = tmp_path / "report"
    (out / "report.md").mkdir(parents=True)
    (out / "report.md" / "mine.txt").write_text("a folder where the report puts a file")
    monkeypatch.chdir(out)  # --out .: the files are moved in one by one
    assert main(smoke(bar_store[0], Path("."))) == 1
    err = capsys.readouterr().err
    kept = Path(re.search(r"it is kept in (\S+)\n", err)[1])  # type: ignore[index]
    made = files(kept)
    assert "fem" in json.loads(made["results.json"])["parts"] and "report.md" in made, sorted(made)
    shutil.rmtree(out / "report.md")
    assert main(smoke(bar_store[0], Path("."))) == 0
    assert files(kept) == made and re.fullmatch(r"report\.unplaced-\d{8}-\d{6}", kept.name), kept
    assert (out / "report.md").is_file()


def test_the_swapped_in_folder_keeps_its_group_and_setgid(bar_store, tmp_path, capsys):
    """A served folder root:daemon 2750 became root:root 0750 (only the mode was copied): the web
    server's group lost it."""
    out = tmp_path / "report"
    out.mkdir()
    gid = next(g for g in (1, 2, 100) if g != os.getgid())
    try:
        os.chown(out, -1, gid)
    except PermissionError:
        pytest.skip("cannot give the folder another group here")
    out.chmod(0o2750)
    assert main(smoke(bar_store[0], out)) == 0
    st = out.stat()
    assert st.st_gid == gid and stat.S_IMODE(st.st_mode) == 0o2750, (st.st_gid, oct(st.st_mode))


def test_a_symlink_loop_out_is_one_line(bar_store, tmp_path, capsys):
    """--out a loop of links: a RuntimeError traceback; now one line, exit status 2."""
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    with pytest.raises(SystemExit) as exit_:
        main(smoke(bar_store[0], tmp_path / "a"))
    err = capsys.readouterr().err
    assert (
        exit_.value.code == 2
        and err.startswith(f"error: --out {tmp_path / 'a'} is a symbolic link")
        and err.count("\n") == 1
    ), err


@pytest.mark.parametrize("how", ["SIGKILL", "SIGINT"])
def test_a_minutes_run_stopped_after_a_build_keeps_its_rows_beside_the_old_report(bar, tmp_path, how):
    """`bench minutes` wrote minutes_rows.json into the live --out after each build: a run killed
    (SIGKILL) after its first build left the old report's results.json beside the new run's rows.
    Then the rows went to the run's scratch folder, --out the old report, whole; but the next run
    into that --out removed the scratch, and a user who stopped an hour-long curve lost the builds
    done. Now the folder is set aside beside --out as NAME.interrupted-TIME: by the stopped run
    itself on Ctrl-C (its path printed), by the next run after a kill (one note line); no run
    removes it."""
    import signal
    import time

    from tests.conftest import write_bar_scene

    scene = write_bar_scene(tmp_path / "scene", bar)
    out = tmp_path / "report"
    out.mkdir()
    old_rows = [{"scene": "bar", "minutes": 30.0, "started": "2026-11-01", "test_relative": 0.1}]
    (out / "results.json").write_text(json.dumps({"smoke": None, "parts": {"minutes": {"rows": old_rows}}}))
    (out / "minutes_rows.json").write_text(json.dumps(old_rows))
    (out / "report.md").write_text("old report\n")
    before = files(out)
    argv = ["bench", "minutes", "--replace", "--scenes", str(scene), "--test-data", str(tmp_path / "test"),
            "--build-minutes", "0.1", "0.1", "--test-paths", "2", "--workers", "0", "--out", str(out)]  # fmt: skip
    proc = subprocess.Popen([sys.executable, "-c", CLI, *argv], cwd=ROOT, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and proc.poll() is None:
            rows = [*tmp_path.glob(".bench-report-*/minutes_rows.json")]
            if rows or files(out) != before:  # a build's row written: in the scratch, or in --out
                break
            time.sleep(0.05)
        assert proc.poll() is None, "the run ended before its first build's row"
        proc.send_signal(getattr(signal, how))
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
        proc.wait()
    assert files(out) == before
    if how == "SIGINT":  # the run sets its rows aside itself, and says where
        assert proc.returncode == 130, err
        (aside,) = tmp_path.glob("report.interrupted-*")
        assert f"note: the minutes rows built so far are kept in {aside / 'minutes_rows.json'}" in err, err
        assert not [*tmp_path.glob(".bench-report-*")]
    else:
        (scratch,) = tmp_path.glob(".bench-report-*")
    redraw = ["bench", "minutes", "--build-minutes", "--scenes", str(scene), "--out", str(out)]  # no builds
    done = subprocess.run([sys.executable, "-c", CLI, *redraw], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    if how == "SIGKILL":  # the next run sets the dead run's rows aside, one line
        (aside,) = tmp_path.glob("report.interrupted-*")
        assert (
            f"note: moved {scratch}, a run stopped before its report went in, to {aside}: its minutes_rows.json "
            "holds the rows built so far" in done.stderr.splitlines()
        ), done.stderr
    assert re.fullmatch(r"report\.interrupted-\d{8}-\d{6}", aside.name), aside.name
    assert json.loads((aside / "minutes_rows.json").read_text())[0]["minutes"] == 0.1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report", aside.name, "scene", "test"]

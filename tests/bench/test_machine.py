"""What a report says it ran on: the commit stamp of the checkout."""

import subprocess

from service.bench.machine import _commit
from service.bench.swap import SCRATCH_PREFIX


def git(root, *args):
    subprocess.run(["git", "-C", str(root), "-c", "user.name=t", "-c", "user.email=t@t", *args], check=True,
                   capture_output=True)  # fmt: skip


def test_the_stamp_sees_untracked_code_and_tells_dirty_trees_apart(tmp_path):
    """_commit() left untracked files out (new code ran under a clean stamp) and stamped every
    dirty tree "+local changes" alike, so --resume took one dirty tree's rows for another's: the
    stamp now counts untracked files (not ignored ones) and hashes the changes."""
    git(tmp_path, "init", "-q")
    (tmp_path / "part.py").write_text("x = 1\n")
    (tmp_path / ".gitignore").write_text("*.log\n")
    git(tmp_path, "add", ".")
    git(tmp_path, "commit", "-q", "-m", "one")
    clean = _commit(tmp_path)
    assert clean and "+" not in clean and clean != "unknown"
    (tmp_path / "run.log").write_text("ignored")
    assert _commit(tmp_path) == clean  # an ignored file is not the code
    (tmp_path / "new_part.py").write_text("def run():\n    return 42\n")
    untracked = _commit(tmp_path)
    assert untracked.startswith(clean + "+local changes ")
    (tmp_path / "new_part.py").write_text("def run():\n    return 43\n")
    assert _commit(tmp_path) not in (untracked, clean)  # its contents count, not only its name
    (tmp_path / "new_part.py").unlink()
    (tmp_path / "part.py").write_text("x = 2\n")
    a = _commit(tmp_path)
    (tmp_path / "part.py").write_text("x = 3\n")
    b = _commit(tmp_path)
    assert a.startswith(clean + "+local changes ") and b.startswith(clean + "+local changes ") and a != b
    (tmp_path / "part.py").write_text("x = 2\n")
    assert _commit(tmp_path) == a  # the same changes, the same stamp


def test_a_report_runs_own_scratch_is_not_a_local_change(tmp_path):
    """A report run's lock beside its --out (made before its first stamp) and its staging
    folder stamped every bench run in reports/ "+local changes": they are the run's, not the code."""
    git(tmp_path, "init", "-q")
    (tmp_path / "part.py").write_text("x = 1\n")
    git(tmp_path, "add", ".")
    git(tmp_path, "commit", "-q", "-m", "one")
    clean = _commit(tmp_path)
    reports = tmp_path / "reports"
    (reports / f"{SCRATCH_PREFIX}latest-x1y2").mkdir(parents=True)
    (reports / f"{SCRATCH_PREFIX}latest.lock").write_text("")
    (reports / f"{SCRATCH_PREFIX}latest-x1y2" / "report.md").write_text("# a report being written")
    assert _commit(tmp_path) == clean
    (reports / "notes.py").write_text("y = 2\n")  # beside them, code still counts
    assert _commit(tmp_path).startswith(clean + "+local changes ")

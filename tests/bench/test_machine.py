"""What a report says it ran on: the commit stamp of the checkout."""

import subprocess

from service.bench.machine import _commit


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

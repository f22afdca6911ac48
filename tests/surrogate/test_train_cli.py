"""`elastreg train` as a user runs it: real processes, a real Dask LocalCluster, what the user
sees when something goes wrong (a wrong --scheduler, a store it cannot write, Ctrl-C)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import write_bar_scene

pytest.importorskip("distributed")
ROOT = Path(__file__).resolve().parents[2]


def train(scene: Path, tmp_path: Path, *flags: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "service.cli", "train", str(scene), "--store", str(tmp_path / "store"),
         "--data", str(tmp_path / "data"), "--hidden", "32", "--rank", "8", "--epochs", "5", *flags],
        capture_output=True, text=True, timeout=timeout, cwd=ROOT,
    )  # fmt: skip


def test_a_build_with_workers_keeps_dasks_info_logs_out_of_the_way(tmp_path, bar):
    """Without -v the cluster's start and stop (~30 INFO lines from distributed) would bury the
    scene's own warnings: only the build's result is printed."""
    scene = write_bar_scene(tmp_path / "scene", bar, samples=6)
    r = train(scene, tmp_path, "--workers", "1")
    assert r.returncode == 0, r.stderr[-3000:]
    assert "INFO distributed" not in r.stderr, r.stderr[-3000:]
    assert "-> " in r.stdout  # the build's one line


@pytest.mark.parametrize("unwritable", ["store", "data"])
def test_a_store_or_data_folder_that_cannot_be_written_is_refused_before_any_work(tmp_path, bar, unwritable, capsys):
    """A file given as --store (or --data) was found only after the data and the training,
    and the error blamed the Dask workers: now refused first, naming the path."""
    from service.cli import main

    scene = write_bar_scene(tmp_path / "scene", bar, samples=6)
    folders = {"store": tmp_path / "store", "data": tmp_path / "data"}
    folders[unwritable].write_text("a file, not a folder")
    rc = main(["train", str(scene), "--store", str(folders["store"]), "--data", str(folders["data"]),
               "--workers", "0", "--hidden", "32", "--rank", "8", "--epochs", "5"])  # fmt: skip
    err = capsys.readouterr().err
    assert rc == 2
    assert str(folders[unwritable]) in err and "not a folder" in err, err
    assert "Dask" not in err
    if unwritable == "store":  # no FEM was solved for a build that could not be kept
        assert not list(folders["data"].rglob("path_*.npz"))

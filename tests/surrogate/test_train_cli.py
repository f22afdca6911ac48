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

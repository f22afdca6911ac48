"""A timed build's warm-up (service/warmup.py): its scratch entry never outlives the build."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

from service.store import remove_stale_builds

ROOT = Path(__file__).resolve().parents[1]

# the build's process dies (kill -9, the OOM killer) right after the warm-up's write
KILLED_AFTER_THE_WRITE = """
import os, signal, sys
from pathlib import Path
sys.path.insert(0, {tests!r})
from conftest import write_bar_scene, grid_tets
import numpy as np
from service.mesh import TetMesh
from service.scene import load_scene
import service.warmup as warmup
from service.build import build

nodes, tets = grid_tets((8, 2, 2), 0.5)
bar, _ = TetMesh.build(nodes, tets, np.flatnonzero(nodes[:, 0] == 0.0))
real = warmup.write_entry
def write_then_die(*args, **kwargs):
    real(*args, **kwargs)
    os.kill(os.getpid(), signal.SIGKILL)
warmup.write_entry = write_then_die
root = Path({root!r})
scene = load_scene(write_bar_scene(root / "scene", bar))
build(scene, root / "store", workers=0, data_root=root / "data", progress=False, minutes=1.0)
"""


def test_a_build_killed_in_its_warm_up_leaves_nothing_the_next_scan_keeps(tmp_path):
    """(review s26) The warm-up wrote into a TemporaryDirectory of the store: a build killed
    there left a hidden .warm-up-* folder (a whole entry, the mesh too) that no scan removed."""
    child = textwrap.dedent(KILLED_AFTER_THE_WRITE).format(tests=str(ROOT / "tests"), root=str(tmp_path))
    r = subprocess.run([sys.executable, "-c", child], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == -9, r.stderr[-3000:]
    store = tmp_path / "store"
    left = [p.name for p in store.iterdir()]
    assert len(left) == 1 and left[0].startswith(".warm-up-"), left  # the killed build's
    assert remove_stale_builds(store) == left
    assert list(store.iterdir()) == []

"""Shared fixtures: small meshes built in code, so the default tests need nothing on disk."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.mesh import TetMesh
from service.phantoms import grid_tets

SHARED = Path(__file__).resolve().parents[2] / "shared"
LIVER = SHARED / "meshes" / "liver_paper"



@pytest.fixture(scope="session")
def bar() -> TetMesh:
    """A 4 x 1 x 1 bar of 8 x 2 x 2 hexes clamped at x = 0 (81 nodes)."""
    nodes, tets = grid_tets((8, 2, 2), 0.5)
    mesh, _ = TetMesh.build(nodes, tets, np.flatnonzero(nodes[:, 0] == 0.0))
    return mesh


@pytest.fixture(scope="session")
def cube() -> TetMesh:
    nodes, tets = grid_tets((2, 2, 2), 0.5)
    mesh, _ = TetMesh.build(nodes, tets, np.flatnonzero(nodes[:, 0] == 0.0))
    return mesh


def needs_liver():
    return pytest.mark.skipif(not LIVER.exists(), reason="../shared/meshes/liver_paper not present")

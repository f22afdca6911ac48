"""Shared fixtures: small meshes built in code, so the default tests need nothing on disk."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from service.mesh import TetMesh

SHARED = Path(__file__).resolve().parents[2] / "shared"
LIVER = SHARED / "meshes" / "liver_paper"

# Kuhn split of the unit cube into 6 tets around the (0,0,0)-(1,1,1) diagonal; corners are
# numbered by bits (x + 2y + 4z), so every hex splits the same way and faces match.
KUHN = [(0, 1, 3, 7), (0, 1, 5, 7), (0, 2, 3, 7), (0, 2, 6, 7), (0, 4, 5, 7), (0, 4, 6, 7)]


def grid_mesh(nx: int, ny: int, nz: int, size=(1.0, 1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Nodes and tets of a box split into nx*ny*nz hexes of 6 tets each."""
    axes = [np.linspace(0.0, s, k + 1) for s, k in zip(size, (nx, ny, nz))]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    idx = np.arange(nodes.shape[0]).reshape(nx + 1, ny + 1, nz + 1)
    tets = []
    for i, j, k in itertools.product(range(nx), range(ny), range(nz)):
        corner = [idx[i + (c & 1), j + ((c >> 1) & 1), k + ((c >> 2) & 1)] for c in range(8)]
        tets += [[corner[q] for q in t] for t in KUHN]
    return nodes, np.array(tets)


@pytest.fixture(scope="session")
def bar() -> TetMesh:
    """A 4 x 1 x 1 bar of 4x2x2 hexes clamped at x = 0 (90 nodes)."""
    nodes, tets = grid_mesh(4, 2, 2, (4.0, 1.0, 1.0))
    mesh, _ = TetMesh.build(nodes, tets, np.flatnonzero(nodes[:, 0] == 0.0))
    return mesh


@pytest.fixture(scope="session")
def cube() -> TetMesh:
    nodes, tets = grid_mesh(2, 2, 2)
    mesh, _ = TetMesh.build(nodes, tets, np.flatnonzero(nodes[:, 0] == 0.0))
    return mesh


def needs_liver():
    return pytest.mark.skipif(not LIVER.exists(), reason="../shared/meshes/liver_paper not present")

"""The procedural meshes: the paper's beam exactly, and a sound, deterministic organ phantom."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from service import phantoms
from service.mesh import components
from service.meshfile import dihedral_angles


@pytest.fixture(scope="module")
def phantom():
    return phantoms.phantom()


def test_beam_is_the_papers():
    beam = phantoms.beam()
    assert beam.n_nodes == 500 and beam.n_tets == 1824 == 304 * 6
    assert (beam.volumes > 0).all()
    assert beam.volumes.sum() == pytest.approx(0.04 * 0.04 * 0.19)
    np.testing.assert_allclose(np.ptp(beam.nodes, axis=0), [0.19, 0.04, 0.04])
    assert beam.fixed.size == 25 and (beam.nodes[beam.fixed, 0] == 0.0).all()
    # Kuhn tets: every one is a sixth of a 1 cm cube, and the split is conforming (a closed,
    # manifold boundary of 2 triangles per outer square)
    np.testing.assert_allclose(beam.volumes, 1e-6 / 6)
    squares = 4 * 19 * 4 + 2 * 4 * 4  # four long sides, two ends
    assert len(beam.surface_faces) == 2 * squares
    assert beam.face_areas.sum() == pytest.approx(2 * (0.19 * 0.04 * 2 + 0.04 * 0.04))


def test_grid_tets_are_positive():
    nodes, tets = phantoms.grid_tets((2, 3, 1), 0.5)
    x = nodes[tets]
    assert (np.linalg.det(x[:, 1:] - x[:, :1]) > 0).all()


def test_phantom_size_and_topology(phantom):
    assert 1000 <= phantom.n_nodes <= 3000
    labels = components(phantom.n_nodes, phantom.tets)
    assert (labels == 0).all()  # one component, every node used
    assert (phantom.volumes > 0).all()
    extent = np.ptp(phantom.nodes, axis=0)
    assert np.all((extent > [0.12, 0.08, 0.05]) & (extent < [0.20, 0.13, 0.10]))
    boundary = trimesh.Trimesh(phantom.nodes, phantom.surface_faces, process=False)
    assert boundary.is_watertight and boundary.is_winding_consistent
    assert boundary.volume == pytest.approx(phantom.volumes.sum())


def test_phantom_quality(phantom):
    worst = dihedral_angles(phantom.nodes, phantom.tets).min(axis=1)
    assert worst.min() > 4.0  # the paper's liver: 4.5 degrees
    assert (worst < 10.0).mean() < 0.02


def test_phantom_hold(phantom):
    surface = phantom.surface_nodes
    assert np.isin(phantom.fixed, surface).all()
    assert 0.05 <= phantom.fixed.size / surface.size <= 0.10
    # one posterior patch: all on the back (+y) side, and connected along the surface
    held = phantom.nodes[phantom.fixed]
    assert (held[:, 1] > 0.02).all()
    sub = phantom.surface_graph[phantom.fixed][:, phantom.fixed]
    from scipy.sparse import csgraph

    assert csgraph.connected_components(sub, directed=False)[0] == 1


def test_phantom_is_deterministic(phantom):
    again = phantoms.phantom()
    assert again.hash == phantom.hash
    np.testing.assert_array_equal(again.tets, phantom.tets)

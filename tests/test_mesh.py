"""TetMesh: validation and repair, the outward boundary, volumes, surface patches, boxes."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from service.mesh import MeshError, TetMesh, signed_volumes
from service.phantoms import grid_tets

UNIT_TET = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])


def test_cube_surface_is_closed_and_outward(cube):
    faces = cube.surface_faces
    assert faces.shape == (6 * 4 * 2, 3)  # 2 x 2 squares per side, 2 triangles each
    centroid = cube.nodes[faces].mean(axis=1)
    outward = ((centroid - 0.5) * cube.face_normals).sum(axis=1)
    assert (outward > 0).all()
    assert cube.face_areas.sum() == pytest.approx(6.0)
    # closed: every boundary edge is shared by exactly two boundary faces
    edges = np.sort(faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert (counts == 2).all()
    assert cube.surface_nodes.size == 26  # all 27 grid nodes but the centre


def test_cube_volumes_positive_and_sum(cube):
    assert (cube.volumes > 0).all()
    assert cube.volumes.sum() == pytest.approx(1.0)
    assert cube.lumped_areas.sum() == pytest.approx(6.0)


def test_inverted_tet_is_reoriented(caplog):
    with caplog.at_level(logging.WARNING, logger="service.mesh"):
        mesh, kept = TetMesh.build(UNIT_TET, [[0, 2, 1, 3]])
    assert kept is None
    assert signed_volumes(UNIT_TET, np.array([[0, 2, 1, 3]]))[0] < 0
    assert mesh.volumes[0] == pytest.approx(1 / 6)
    assert "re-oriented 1 inverted" in caplog.text


def test_degenerate_tet_is_refused():
    nodes = np.vstack([UNIT_TET, [[1.0, 1.0, 0.0]]])  # node 4 is coplanar with 0, 1, 2
    with pytest.raises(MeshError, match="degenerate"):
        TetMesh.build(nodes, [[0, 1, 2, 3], [0, 1, 2, 4]])


def test_repeated_node_is_refused():
    with pytest.raises(MeshError, match="repeat a node"):
        TetMesh.build(UNIT_TET, [[0, 1, 1, 3]])


def test_two_components_are_refused():
    nodes = np.vstack([UNIT_TET, UNIT_TET + 5.0])
    with pytest.raises(MeshError, match="2 separate components"):
        TetMesh.build(nodes, [[0, 1, 2, 3], [4, 5, 6, 7]])


def test_the_components_message_counts_only_used_nodes():
    """An unused node between two bodies is a component of its own to scipy: it was listed as an
    empty one ("node counts [181, 167, 0, 0, 0]")."""
    nodes = np.vstack([UNIT_TET, [[9.0, 9, 9], [7.0, 7, 7]], UNIT_TET + 5.0])  # nodes 4 and 5 unused
    with pytest.raises(MeshError, match=r"2 separate components \(node counts \[4, 4\]\)"):
        TetMesh.build(nodes, [[0, 1, 2, 3], [6, 7, 8, 9]])


def test_unused_node_is_dropped_with_map(caplog):
    nodes = np.vstack([UNIT_TET[:2], [[9.0, 9, 9]], UNIT_TET[2:]])  # node 2 is unused
    with caplog.at_level(logging.WARNING, logger="service.mesh"):
        mesh, kept = TetMesh.build(nodes, [[0, 1, 3, 4]], fixed=[2, 4])
    assert kept.tolist() == [0, 1, 3, 4]
    np.testing.assert_array_equal(mesh.nodes, nodes[kept])
    assert mesh.tets.tolist() == [[0, 1, 2, 3]]
    assert mesh.fixed.tolist() == [3]  # old 4 -> new 3; the dropped 2 is gone
    assert "dropped 1 nodes" in caplog.text


def test_bad_indices_and_shapes_are_refused():
    with pytest.raises(MeshError, match="outside"):
        TetMesh.build(UNIT_TET, [[0, 1, 2, 4]])
    with pytest.raises(MeshError, match="non-empty"):
        TetMesh.build(UNIT_TET, np.zeros((0, 4), int))
    with pytest.raises(MeshError, match="fixed node ids"):
        TetMesh.build(UNIT_TET, [[0, 1, 2, 3]], fixed=[7])


def test_surface_patch_is_free_connected_and_near(bar):
    free = set(bar.free_surface_nodes.tolist())
    top = np.flatnonzero(np.isclose(bar.nodes, [2.0, 0.5, 1.0]).all(axis=1))[0]
    patch = bar.surface_patch(top, 9)
    assert patch[0] == top and len(patch) == 9 and len(set(patch.tolist())) == 9
    assert set(patch.tolist()) <= free
    assert np.linalg.norm(bar.nodes[patch] - bar.nodes[top], axis=1).max() <= 1.2
    # next to the clamp the patch skips the fixed nodes and stays on the surface
    near = np.flatnonzero(np.isclose(bar.nodes, [1.0, 0.5, 1.0]).all(axis=1))[0]
    patch = bar.surface_patch(near, 12)
    assert set(patch.tolist()) <= free and not np.isin(patch, bar.fixed).any()


def test_nodes_in_box(cube):
    left = cube.nodes_in_box([0, 0, 0], [0.5, 1, 1])
    assert left.size == 18 and (cube.nodes[left, 0] <= 0.5).all()
    corner = cube.nodes_in_box([0.9, 0.9, 0.9], [2, 2, 2])
    assert cube.nodes[corner].tolist() == [[1.0, 1.0, 1.0]]


def test_free_surface_excludes_fixed(bar):
    assert not np.isin(bar.free_surface_nodes, bar.fixed).any()
    assert bar.fixed.size == 9 and (bar.nodes[bar.fixed, 0] == 0).all()
    nodes, tets = grid_tets((1, 1, 1), 1.0)
    mesh, _ = TetMesh.build(nodes, tets)
    assert mesh.free_surface_nodes.size == 8 and mesh.surface_faces.shape == (12, 3)


def test_a_patch_normal_is_the_unit_outward_normal_of_its_face(bar):
    """The bar's free end (x = 4) and its top (z = 1): unit vectors close to +x and +z (the
    edge nodes' own normals lean over the sides, and the tets' diagonals are not symmetric)."""
    end = np.flatnonzero(bar.nodes[:, 0] == bar.nodes[:, 0].max())
    top = np.flatnonzero((bar.nodes[:, 2] == bar.nodes[:, 2].max()) & (bar.nodes[:, 0] > 1.0))
    for nodes, axis in ((end, 0), (top, 2)):
        n = bar.patch_normal(nodes)
        assert abs(np.linalg.norm(n) - 1.0) < 1e-12 and n[axis] > 0.95


@pytest.mark.parametrize("shift", [[1.0, 1.0, 0.0], [1.0, 1.0, 1.0]])  # along an edge; at a point
def test_parts_that_touch_without_a_shared_face_are_refused(shift):
    """Connected through a node or an edge, the two blocks could turn about the contact: not one
    body (a build on it failed every path, or trained on one sample)."""
    n, t = grid_tets((2, 2, 2), 0.5)
    nodes, inverse = np.unique(np.vstack([n, n + shift]).round(9), axis=0, return_inverse=True)
    tets = inverse.ravel()[np.vstack([t, t + len(n)])]
    with pytest.raises(MeshError, match="touch only along an edge or at a point"):
        TetMesh.build(nodes, tets)
    TetMesh.build(*grid_tets((4, 2, 2), 0.5))  # blocks sharing a face are one body


def test_a_face_in_three_tets_is_refused():
    n, t = grid_tets((1, 1, 1), 1.0)
    with pytest.raises(MeshError, match="more than two tets"):
        TetMesh.build(n, np.vstack([t, t[:1]]))


def test_a_tangled_mesh_is_refused_where_one_of_mixed_vertex_order_is_reoriented(caplog):
    """Flipping every negative tet is right where a file lists tets in mixed vertex order, but an
    interior node pushed through a face leaves tets that overlap once flipped (1 % more volume
    than the boundary encloses on the 181-node liver): the FEM counted the overlap twice."""
    nodes, tets = grid_tets((3, 3, 3), 1.0 / 3.0)
    mixed = tets.copy()
    mixed[::3, 2], mixed[::3, 3] = tets[::3, 3], tets[::3, 2]  # a third of them listed the other way round
    with caplog.at_level(logging.WARNING, logger="service.mesh"):
        mesh, _ = TetMesh.build(nodes, mixed)
    assert "re-oriented" in caplog.text and mesh.volumes.sum() == pytest.approx(1.0)

    inner = int(np.flatnonzero((np.abs(nodes - 0.5) < 0.2).all(axis=1))[0])  # an interior node
    t = int(np.flatnonzero((tets == inner).any(axis=1))[0])
    face = nodes[tets[t][tets[t] != inner]].mean(axis=0)
    tangled = nodes.copy()
    tangled[inner] = face + 1.5 * (face - nodes[inner])  # through the opposite face, as far again beyond it
    assert (signed_volumes(tangled, tets) < 0).any()  # what the loader "repaired"
    with pytest.raises(MeshError, match=r"tangled: \d+ interior faces have both their tets on one side"):
        TetMesh.build(tangled, tets)


def test_tets_on_coincident_nodes_are_refused_with_how_many(cube):
    """Before: a copy of an interior node used by half its tets was accepted as a body cracked
    along the slit (its faces became surface, loads and all), and a mesh whose every node was
    copied was refused as '2 separate components ... one scene per body'. Now both say how many
    nodes coincide and that they need merging."""
    nodes, tets = cube.nodes, cube.tets.copy()
    centre = int(np.flatnonzero((nodes == 0.5).all(axis=1))[0])
    slit = np.vstack([nodes, nodes[centre]])  # the copy, last
    half = np.flatnonzero((tets == centre).any(axis=1))[::2]
    tets[half] = np.where(tets[half] == centre, len(nodes), tets[half])
    with pytest.raises(MeshError) as exc:
        TetMesh.build(slit, tets)
    said = str(exc.value)
    assert said.startswith("1 nodes used by tets coincide with another node") and "merge coincident nodes" in said
    assert "[0.5, 0.5, 0.5]" in said and "\n" not in said

    copied = np.vstack([nodes, nodes])  # every node twice, half the tets on the copies
    split = cube.tets.copy()
    split[::2] += len(nodes)
    both = np.intersect1d(cube.tets[::2], cube.tets[1::2]).size  # the nodes of both halves: used twice
    with pytest.raises(MeshError, match=rf"^{both} nodes used by tets coincide with another node"):
        TetMesh.build(copied, split)

    from service.mesh import coincident_nodes

    near = np.vstack([nodes, nodes[centre] + 1e-6])  # 1e-6 of the size: a distinct node
    coincident_nodes(near, tets)


def test_a_copy_astride_the_tolerance_grid_is_found_and_a_stray_node_judges_no_scale(cube):
    """Review of 7eaf269: a copy 2e-13 x the size away, astride a cell of the rounding grid, passed
    (then refused as 'parts that touch along an edge'); and the scale check measured nodes no tet
    uses, so one stray node 2e9 units out refused a good file's scale."""
    from service.mesh import coincident_nodes
    from service.meshfile import scaled

    nodes, tets = cube.nodes.copy(), cube.tets.copy()
    centre = int(np.flatnonzero((nodes == 0.5).all(axis=1))[0])
    span = float(np.linalg.norm(np.ptp(nodes, axis=0)))
    edge = (np.floor(0.5 / (span * 1e-9)) + 0.5) * span * 1e-9  # a rounding cell's edge, along x
    nodes[centre, 0] = edge - 1e-13 * span
    slit = np.vstack([nodes, nodes[centre] + [2e-13 * span, 0, 0]])
    half = np.flatnonzero((tets == centre).any(axis=1))[::2]
    tets[half] = np.where(tets[half] == centre, len(nodes), tets[half])
    with pytest.raises(MeshError, match=r"^1 nodes used by tets coincide with another node"):
        coincident_nodes(slit, tets)

    stray = np.vstack([cube.nodes, [2e9, 0, 0]])  # used by no tet: dropped later
    assert np.array_equal(scaled(stray, 0.001, "stray.vtu", cube.tets), stray * 0.001)

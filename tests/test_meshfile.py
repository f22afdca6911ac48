"""Mesh files: meshio formats, gmsh files with boundary triangles, surfaces through tetgen."""

from __future__ import annotations

import logging

import meshio
import numpy as np
import pytest
import trimesh

from service.mesh import MeshError, TetMesh
from service.meshfile import dihedral_angles, load_mesh
from service.phantoms import grid_tets
from tests.conftest import LIVER, needs_liver


@pytest.fixture(scope="module")
def box() -> tuple[np.ndarray, np.ndarray]:
    """A 3 x 2 x 2 hex box of 1 cm cells (positively oriented Kuhn tets)."""
    return grid_tets((3, 2, 2), 0.01)


@needs_liver()
def test_paper_liver_msh_loads_tets_only():
    m = load_mesh(LIVER / "liver.msh")
    assert m.nodes.shape == (3046, 3) and m.tets.shape == (10703, 4)
    assert m.kept is None and not m.tetrahedralised and m.n_source_nodes == 3046
    assert m.quality.volume > 0 and m.quality.min_dihedral > 1.0
    assert m.to_mesh().n_nodes == 3046


@pytest.mark.parametrize(
    "name, fmt",
    [("m.vtu", None), ("m.vtk", None), ("m.msh", "gmsh22"), ("m.mesh", None)],
)
def test_meshio_formats_round_trip(tmp_path, box, name, fmt):
    nodes, tets = box
    path = tmp_path / name
    kwargs = {"file_format": fmt, "binary": False} if fmt else {}
    meshio.write(path, meshio.Mesh(nodes, [("tetra", tets)]), **kwargs)
    m = load_mesh(path)
    np.testing.assert_allclose(m.nodes, nodes, atol=1e-12)
    np.testing.assert_array_equal(m.tets, tets)
    assert m.kept is None and m.source == path and not m.renumbered


def test_boundary_cells_ignored_and_unused_nodes_mapped(tmp_path, box):
    nodes, tets = box
    extra = np.vstack([nodes[:5], [[1.0, 1.0, 1.0]], nodes[5:]])  # an unused node at index 5
    tets = np.where(tets >= 5, tets + 1, tets)
    tris = TetMesh(nodes, grid_tets((3, 2, 2), 0.01)[1]).surface_faces
    tris = np.where(tris >= 5, tris + 1, tris)
    path = tmp_path / "with_tris.msh"
    cells = [("triangle", tris), ("tetra", tets), ("vertex", np.array([[5]]))]
    meshio.write(path, meshio.Mesh(extra, cells), file_format="gmsh22", binary=False)
    m = load_mesh(path)
    assert m.n_source_nodes == len(extra) and len(m.nodes) == len(nodes)
    assert 5 not in m.kept.tolist() and m.renumbered
    np.testing.assert_allclose(m.nodes, nodes)
    assert m.source_to_mesh()[5] == -1 and m.source_to_mesh()[6] == 5


def test_scale_applies(tmp_path, box):
    nodes, tets = box
    path = tmp_path / "mm.vtu"
    meshio.write(path, meshio.Mesh(nodes * 1000.0, [("tetra", tets)]))
    m = load_mesh(path, scale=0.001)
    np.testing.assert_allclose(m.nodes, nodes, atol=1e-15)
    assert m.quality.volume == pytest.approx(0.03 * 0.02 * 0.02)


def test_inverted_tets_are_repaired(tmp_path, box, caplog):
    nodes, tets = box
    flipped = tets.copy()
    flipped[::2, [2, 3]] = flipped[::2, [3, 2]]
    path = tmp_path / "flipped.vtu"
    meshio.write(path, meshio.Mesh(nodes, [("tetra", flipped)]))
    m = load_mesh(path)
    assert m.to_mesh().volumes.min() > 0
    assert "re-oriented" in caplog.text


def test_file_without_tets_names_the_file(tmp_path, box):
    nodes, tets = box
    path = tmp_path / "surface_only.vtu"
    tris = TetMesh(nodes, tets).surface_faces
    meshio.write(path, meshio.Mesh(nodes, [("triangle", tris)]))
    with pytest.raises(MeshError, match=r"surface_only\.vtu: no tetrahedra"):
        load_mesh(path)


def test_dropped_volume_cells_are_a_warning_naming_kinds_and_counts(tmp_path, box, caplog):
    """Hexes or wedges beside the tets are part of the body: dropping them is said at WARNING
    (the command line shows it), by kind and count; boundary triangles and vertices stay quiet."""
    nodes, tets = box
    tris = TetMesh(nodes, tets).surface_faces
    hexes = np.arange(16).reshape(2, 8)
    cells = [("tetra", tets), ("hexahedron", hexes), ("wedge", np.arange(6)[None]), ("triangle", tris)]
    path = tmp_path / "mixed.vtu"
    meshio.write(path, meshio.Mesh(nodes, cells))
    caplog.set_level(logging.INFO, logger="service.meshfile")
    m = load_mesh(path)
    np.testing.assert_array_equal(m.tets, tets)  # the tets, as before
    (warning,) = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert "mixed.vtu: dropped 2 hexahedron, 1 wedge cells (only tets are used)" in warning.getMessage()

    caplog.clear()
    quiet = tmp_path / "with_tris.vtu"
    meshio.write(quiet, meshio.Mesh(nodes, [("tetra", tets), ("triangle", tris), ("vertex", np.array([[0]]))]))
    load_mesh(quiet)
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


def test_a_legacy_gmsh_files_dropped_hexes_are_a_warning(tmp_path, box, caplog):
    nodes, tets = box
    rows = [f"{i + 1} 4 1 1 4 " + " ".join(str(v + 1) for v in t) for i, t in enumerate(tets)]
    rows.append(f"{len(rows) + 1} 5 1 1 8 " + " ".join(str(v) for v in range(1, 9)))  # a hexahedron
    rows.append(f"{len(rows) + 1} 2 1 1 3 1 2 3")  # a boundary triangle: quiet
    text = ["$NOD", str(len(nodes))] + [f"{i + 1} {x} {y} {z}" for i, (x, y, z) in enumerate(nodes)]
    text += ["$ENDNOD", "$ELM", str(len(rows)), *rows, "$ENDELM", ""]
    path = tmp_path / "sofa.msh"
    path.write_text("\n".join(text))
    m = load_mesh(path)
    assert len(m.tets) == len(tets)
    (warning,) = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert "sofa.msh: dropped 1 hexahedron cells" in warning.getMessage()


def _gmsh1(path, nodes: np.ndarray, tets: np.ndarray, labels: np.ndarray) -> None:
    """A legacy gmsh v1 file of tets whose nodes carry `labels` (gmsh's own, any whole numbers)."""
    rows = [f"{i + 1} 4 1 1 4 " + " ".join(str(labels[v]) for v in t) for i, t in enumerate(tets)]
    text = ["$NOD", str(len(nodes))] + [
        f"{lab} {x:.17g} {y:.17g} {z:.17g}" for lab, (x, y, z) in zip(labels, nodes, strict=True)
    ]
    path.write_text("\n".join([*text, "$ENDNOD", "$ELM", str(len(rows)), *rows, "$ENDELM", ""]))


def test_a_legacy_gmsh_files_huge_labels_are_mapped_and_negative_ones_refused(tmp_path, box):
    """Before: the labels were mapped through an array as long as the largest (a label of 1e11
    asked for 745 GiB: a traceback), and a -5 wrapped round to another node, reported as a
    tangled mesh. Now large labels load as any others and a negative one is named."""
    nodes, tets = box
    labels = np.arange(1, len(nodes) + 1)
    labels[0], labels[5] = 10**11, 2**62  # far past any array this machine could hold
    _gmsh1(tmp_path / "huge.msh", nodes, tets, labels)
    m = load_mesh(tmp_path / "huge.msh")
    np.testing.assert_array_equal(m.nodes, nodes)
    np.testing.assert_array_equal(m.tets, tets)

    labels[0], labels[3] = -5, -7
    _gmsh1(tmp_path / "negative.msh", nodes, tets, labels)
    with pytest.raises(MeshError) as exc:
        load_mesh(tmp_path / "negative.msh")
    assert (
        str(exc.value)
        == f"{tmp_path / 'negative.msh'}: node labels must be >= 0 (gmsh numbers them from 1), got -7, -5"
    )

    past = np.arange(1, len(nodes) + 1).astype(object)
    past[3] = 2**64  # past int64: no label gmsh writes
    _gmsh1(tmp_path / "overflow.msh", nodes, tets, past)
    with pytest.raises(MeshError, match="not a readable gmsh v1 file"):
        load_mesh(tmp_path / "overflow.msh")


def _quadratic(nodes: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The corners, then one mid-edge node per tet edge (gmsh's ten-node order: corners first)."""
    edges = tets[:, [0, 1, 2, 0, 1, 2]], tets[:, [1, 2, 0, 3, 3, 3]]
    mid = len(nodes) + np.arange(6 * len(tets)).reshape(len(tets), 6)
    middles = (0.5 * (nodes[edges[0]] + nodes[edges[1]])).reshape(-1, 3)
    return np.vstack([nodes, middles]), np.hstack([tets, mid])


def test_a_legacy_gmsh_files_quadratic_tets_keep_their_corners(tmp_path, box, caplog):
    """Before: type 11 was dropped with a warning (and a file of them alone refused), while
    meshio's tetra10 kept its corners. Now both give the linear mesh of the corners."""
    corners, tets = box
    nodes, tets10 = _quadratic(corners, tets[:2])  # two ten-node tets
    rows = [f"{i + 1} 11 1 1 10 " + " ".join(str(v + 1) for v in t) for i, t in enumerate(tets10)]
    text = ["$NOD", str(len(nodes))] + [f"{i + 1} {x:.17g} {y:.17g} {z:.17g}" for i, (x, y, z) in enumerate(nodes)]
    text += ["$ENDNOD", "$ELM", str(len(rows)), *rows, "$ENDELM", ""]
    path = tmp_path / "quadratic.msh"
    path.write_text("\n".join(text))
    caplog.set_level(logging.INFO, logger="service.meshfile")
    m = load_mesh(path)
    assert "cells" not in caplog.text  # no "dropped 2 tetra10 cells"; the unused mid-edge nodes are said
    linear = tmp_path / "linear.vtu"
    meshio.write(linear, meshio.Mesh(corners, [("tetra", tets[:2])]))
    same = load_mesh(linear)  # its unused corners go as the mid-edge nodes do
    np.testing.assert_array_equal(m.nodes, same.nodes)
    np.testing.assert_array_equal(m.tets, same.tets)
    np.testing.assert_array_equal(m.kept, same.kept)
    meshio_path = tmp_path / "quadratic.vtu"  # the meshio path, the one to agree with
    meshio.write(meshio_path, meshio.Mesh(nodes, [("tetra10", tets10)]))
    by_meshio = load_mesh(meshio_path)
    np.testing.assert_array_equal(m.nodes, by_meshio.nodes)
    np.testing.assert_array_equal(m.tets, by_meshio.tets)
    np.testing.assert_array_equal(m.kept, by_meshio.kept)


def test_a_file_of_hexes_alone_is_a_one_line_refusal(tmp_path, box):
    nodes, _ = box
    path = tmp_path / "hexes.vtu"
    meshio.write(path, meshio.Mesh(nodes, [("hexahedron", np.arange(16).reshape(2, 8))]))
    with pytest.raises(MeshError) as info:
        load_mesh(path)
    assert "hexes.vtu: no tetrahedra in this file (cells: hexahedron); give a tetrahedral" in str(info.value)
    assert "\n" not in str(info.value)


def test_bad_meshes_name_the_file(tmp_path):
    tet = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    path = tmp_path / "two.vtu"
    two = np.array([[0, 1, 2, 3], [4, 5, 6, 7]])
    meshio.write(path, meshio.Mesh(np.vstack([tet, tet + 3]), [("tetra", two)]))
    with pytest.raises(MeshError, match=r"two\.vtu: .*2 separate components"):
        load_mesh(path)
    flat = tmp_path / "flat.vtu"
    pts = np.vstack([tet, [[1.0, 1.0, 0.0]]])
    meshio.write(flat, meshio.Mesh(pts, [("tetra", np.array([[0, 1, 2, 3], [0, 1, 2, 4]]))]))
    with pytest.raises(MeshError, match=r"flat\.vtu: .*degenerate"):
        load_mesh(flat)
    with pytest.raises(MeshError, match="no such mesh file"):
        load_mesh(tmp_path / "missing.vtu")
    junk = tmp_path / "junk.xyz"
    junk.write_text("not a mesh")
    with pytest.raises(MeshError, match=r"junk\.xyz: meshio could not read it"):
        load_mesh(junk)


def test_closed_surface_is_tetrahedralised(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.05)
    path = tmp_path / "ball.stl"
    sphere.export(path)
    m = load_mesh(path)
    assert m.tetrahedralised and m.kept is None and m.renumbered  # nodes added inside
    mesh = m.to_mesh()
    assert (mesh.volumes > 0).all()
    assert mesh.volumes.sum() == pytest.approx(sphere.volume, rel=1e-6)
    # the surface is kept as given: its vertices come first and form the whole boundary
    nv = len(sphere.vertices)
    assert mesh.surface_nodes.tolist() == list(range(nv))
    assert len(mesh.surface_faces) == len(sphere.faces)
    np.testing.assert_allclose(np.linalg.norm(mesh.nodes[:nv], axis=1), 0.05, rtol=1e-6)
    assert dihedral_angles(mesh.nodes, mesh.tets).min() > 5.0
    again = load_mesh(path)
    np.testing.assert_array_equal(again.nodes, m.nodes)
    np.testing.assert_array_equal(again.tets, m.tets)


def test_surface_scale_and_max_volume(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=50.0)  # millimetres
    path = tmp_path / "ball.obj"
    sphere.export(path)
    coarse = load_mesh(path, scale=0.001)
    fine = load_mesh(path, scale=0.001, max_volume=2e-7)
    assert np.linalg.norm(coarse.nodes, axis=1).max() == pytest.approx(0.05, rel=1e-6)
    assert len(fine.tets) > len(coarse.tets)
    assert fine.quality.volume == pytest.approx(coarse.quality.volume)


def test_open_surface_is_refused(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=1)
    holed = trimesh.Trimesh(sphere.vertices, sphere.faces[1:], process=False)
    path = tmp_path / "holed.ply"
    holed.export(path)
    with pytest.raises(MeshError, match=r"holed\.ply: the surface is not watertight \(3 open"):
        load_mesh(path)


def test_a_self_intersecting_surface_is_refused_and_the_process_goes_on(tmp_path, monkeypatch):
    """tetgen refuses it and then corrupts its process's heap, so it runs in a child process;
    its scratch files stay out of the working directory."""
    a, b = trimesh.creation.box((1, 1, 1)), trimesh.creation.box((1, 1, 1))
    b.apply_translation([0.5, 0.5, 0.5])
    trimesh.util.concatenate([a, b]).export(tmp_path / "crossed.stl")
    trimesh.creation.box((1, 1, 1)).export(tmp_path / "box.stl")
    monkeypatch.chdir(tmp_path)
    for _ in range(2):
        with pytest.raises(MeshError, match="self-intersecting"):
            load_mesh(tmp_path / "crossed.stl")
        assert load_mesh(tmp_path / "box.stl").tets.shape[1] == 4
    assert sorted(p.name for p in tmp_path.iterdir()) == ["box.stl", "crossed.stl"]


def test_a_surfaces_node_ids_are_its_files_vertex_ids(tmp_path):
    """A scene names nodes by the file's ids: a vertex no face uses (dropped) or one written
    twice (merged) must not shift the others."""
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    V, F = np.asarray(box.vertices), np.asarray(box.faces)
    verts = np.vstack([[[5.0, 5.0, 5.0]], V, V[2:3]])  # an unused vertex first, a copy of vertex 2 last
    faces = np.where(F == 2, 9, F + 1)  # faces use the copy
    lines = [f"v {x} {y} {z}" for x, y, z in verts] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    (tmp_path / "box.obj").write_text("\n".join(lines) + "\n")
    loaded = load_mesh(tmp_path / "box.obj")
    ids = loaded.source_to_mesh()
    assert loaded.n_source_nodes == 10 and ids[0] == -1
    np.testing.assert_allclose(loaded.nodes[ids[1:]], verts[1:])
    assert ids[3] == ids[9]  # the copy is the same node
    # and back: each mesh node's file id names that node again (held_out_sites.py writes them;
    # before, it wrote mesh ids, and a scene read them as file ids one vertex off)
    back = loaded.mesh_to_source()
    assert back.shape == (len(loaded.nodes),) and (back[ids[1:]] >= 1).all()
    np.testing.assert_array_equal(ids[back[ids[1:]]], ids[1:])

"""Ground truth that is not the method's own discrete model: the same organ on a finer mesh.

Scoring a registration against sequences that the same P1 mesh produced rewards the method for
reproducing its own discretisation (an "inverse crime"). Here every tet is split into eight at
its edge midpoints: the coarse nodes keep their ids (the finer mesh lists them first), so a
truth on the fine mesh reads straight off at the coarse nodes, loads on coarse nodes act on the
same points, and the camera's clouds sample the fine surface. Or ten-node tets on the mesh
itself, whose nodes are the same: nearer the converged solution at that cost (`TRUTHS`).
"""

from __future__ import annotations

import numpy as np

from ..fem.material import NeoHookean
from ..fem.quadratic import QuadraticFEM
from ..mesh import TetMesh, edge_midpoints

Array = np.ndarray

#: the eight children in local ids: vertices 0-3, then midpoints 4-9 in TET_EDGES' order; four
#: corner tets and an octahedron cut along its 4-9 diagonal (m01-m23)
_CHILDREN = np.array([
    [0, 4, 5, 6], [4, 1, 7, 8], [5, 7, 2, 9], [6, 8, 9, 3],
    [4, 5, 6, 9], [4, 5, 7, 9], [4, 6, 8, 9], [4, 7, 8, 9],
])  # fmt: skip


def subdivide(mesh: TetMesh) -> TetMesh:
    """Each tet into eight; coarse nodes keep their ids; an edge between two fixed nodes has a
    fixed midpoint (the Dirichlet surface stays the same surface). Shape: n + edges nodes."""
    n = mesh.n_nodes
    edges, mid = edge_midpoints(n, mesh.tets)
    nodes = np.vstack([mesh.nodes, 0.5 * (mesh.nodes[edges[:, 0]] + mesh.nodes[edges[:, 1]])])
    local = np.hstack([mesh.tets, mid])  # (t, 10)
    tets = local[:, _CHILDREN].reshape(-1, 4)
    fixed_mask = np.zeros(n, bool)
    fixed_mask[mesh.fixed] = True
    fixed = np.concatenate([mesh.fixed, n + np.flatnonzero(fixed_mask[edges].all(axis=1))])
    fine, kept = TetMesh.build(nodes, tets, fixed)
    assert kept is None  # every node is used: no renumbering
    return fine


def fine_patch(coarse: TetMesh, fine: TetMesh, tool: Array) -> Array:
    """The fine mesh's nodes of a coarse surface patch: its nodes and the surface midpoints of
    the edges between them, so a load spread evenly over them is a load over the patch's area
    (the coarse nodes alone would be point loads, which a finer mesh resolves as dimples)."""
    tool = np.asarray(tool, np.int64)
    inside = np.zeros(coarse.n_nodes, bool)
    inside[tool] = True
    mids = coarse.n_nodes + np.flatnonzero(inside[coarse_edges(coarse)].all(axis=1))
    on_surface = np.zeros(fine.n_nodes, bool)
    on_surface[fine.surface_nodes] = True
    return np.concatenate([tool, mids[on_surface[mids]]])


def coarse_edges(coarse: TetMesh) -> Array:
    """The coarse mesh's edges (e, 2), in the order subdivide() numbers their midpoints."""
    return edge_midpoints(coarse.n_nodes, coarse.tets)[0]


def face_midpoints(mesh: TetMesh, faces: Array) -> Array:
    """The midpoint ids (as subdivide() numbers them) of each triangle's edges ab, bc, ca.
    Shape: (f, 3) -> (f, 3)."""
    edges = coarse_edges(mesh)
    keys = edges[:, 0] * mesh.n_nodes + edges[:, 1]
    pairs = np.sort(np.asarray(faces)[:, [[0, 1], [1, 2], [2, 0]]], axis=2)  # (f, 3, 2)
    return mesh.n_nodes + np.searchsorted(keys, pairs[..., 0] * mesh.n_nodes + pairs[..., 1])


#: the truths a benchmark may score against: linear tets on the mesh subdivided once, or
#: ten-node tets on the mesh itself (the same nodes; nearer the converged solution,
#: docs/performance.md "Quadratic tets")
TRUTHS = ("subdivided", "quadratic")


def quadratic_truth(coarse: TetMesh, fine: TetMesh, material: NeoHookean) -> QuadraticFEM:
    """Ten-node tets on `coarse`, on `fine`'s nodes (subdivide(coarse))."""
    return QuadraticFEM(fine, material, elements=coarse)


def traction_shares(coarse: TetMesh, fine: TetMesh, tool: Array, spread: Array) -> Array:
    """Each of `spread`'s nodes' share (summing to 1) of a uniform traction over the coarse
    surface triangles whose nodes all lie in `tool`, as ten-node tets take it: a straight
    six-node triangle's corners take nothing and its edge midpoints a third of its force each."""
    inside = np.zeros(coarse.n_nodes, bool)
    inside[tool] = True
    faces = coarse.surface_faces[inside[coarse.surface_faces].all(axis=1)]
    x = coarse.nodes[faces]
    area = 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)
    mids = face_midpoints(coarse, faces)
    load = np.bincount(mids.ravel(), weights=np.repeat(area / 3.0, 3), minlength=fine.n_nodes)
    if not np.isin(np.flatnonzero(load), spread).all():
        raise ValueError("the traction's midpoints lie outside the spread patch")
    return load[spread] / load.sum()

"""Ground truth that is not the method's own discrete model: the same organ on a finer mesh.

Scoring a registration against sequences that the same P1 mesh produced rewards the method for
reproducing its own discretisation (an "inverse crime"). Here every tet is split into eight at
its edge midpoints: the coarse nodes keep their ids (the finer mesh lists them first), so a
truth on the fine mesh reads straight off at the coarse nodes, loads on coarse nodes act on the
same points, and the camera's clouds sample the fine surface.
"""

from __future__ import annotations

import numpy as np

from ..mesh import TetMesh

Array = np.ndarray

#: the tet's six edges as local vertex pairs, in the order the midpoints are numbered below
_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
#: the eight children in local ids: vertices 0-3, then midpoints 4-9 in _EDGES' order; four
#: corner tets and an octahedron cut along its 4-9 diagonal (m01-m23)
_CHILDREN = np.array([
    [0, 4, 5, 6], [4, 1, 7, 8], [5, 7, 2, 9], [6, 8, 9, 3],
    [4, 5, 6, 9], [4, 5, 7, 9], [4, 6, 8, 9], [4, 7, 8, 9],
])  # fmt: skip


def subdivide(mesh: TetMesh) -> TetMesh:
    """Each tet into eight; coarse nodes keep their ids; an edge between two fixed nodes has a
    fixed midpoint (the Dirichlet surface stays the same surface). Shape: n + edges nodes."""
    n = mesh.n_nodes
    edges, mid = edge_midpoints(mesh)
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
    return edge_midpoints(coarse)[0]


def edge_midpoints(mesh: TetMesh) -> tuple[Array, Array]:
    """The mesh's edges (e, 2), sorted, and each tet's six midpoint ids n + edge index in _EDGES'
    order (t, 6): the finer mesh's numbering, and a ten-node tet's."""
    pairs = np.sort(mesh.tets[:, _EDGES], axis=2).reshape(-1, 2)  # (6 t, 2)
    edges, inverse = np.unique(pairs, axis=0, return_inverse=True)
    return edges, mesh.n_nodes + inverse.reshape(-1, 6)

"""Procedural default meshes (the shipped scenes' bodies), built in code so nothing is on disk.

Both are deterministic on one machine: the same arrays on every call (no randomness; the
phantom's bumps are fixed constants and tetgen is deterministic for a given input). The beam is
the same on every machine; the phantom's interior is tetgen's, which depends on tetgen's build:
1,620 nodes and 7,827 tets where the shipped entry was built, 1,636 and 7,931 on another machine
with the same code. So the phantom's mesh hash may differ from machine to machine, and a stored
model carries its own mesh (the shipped phantom's is the one it serves, whatever the generator
gives here).
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp

from .mesh import TetMesh

log = logging.getLogger(__name__)

Array = np.ndarray

#: Kuhn (Freudenthal) split of a hex into 6 tets around its (0,0,0)-(1,1,1) diagonal. Corners are
#: numbered by bits (x + 2y + 4z); with the same split in every hex, neighbouring hexes cut their
#: shared face along the same diagonal, so the mesh is conforming. Each tet is listed positively
#: oriented (det[b-a, c-a, d-a] > 0), so TetMesh.build has nothing to repair.
KUHN = np.array([[0, 1, 3, 7], [0, 5, 1, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 6, 4, 7]])

#: Smooth deformations of the phantom's ellipsoid: (direction, relative amplitude, width).
#: Von Mises bumps exp((d . c - 1) / w^2) on the unit sphere: low frequency by construction, and
#: a radial height field can never self-intersect (the body stays star-shaped).
PHANTOM_BUMPS: tuple[tuple[tuple[float, float, float], float, float], ...] = (
    ((1.0, 0.35, 0.3), 0.22, 0.55),  # a rounded right lobe
    ((-0.8, 0.6, 0.1), 0.16, 0.45),  # a smaller left lobe
    ((0.1, -0.3, -1.0), -0.25, 0.50),  # a hollow underneath (the visceral face)
    ((-0.15, -1.0, 0.05), -0.18, 0.40),  # a notch on the front edge
    ((0.35, 0.2, 1.0), 0.16, 0.60),  # a domed top (the diaphragmatic face)
)
PHANTOM_AXES = (0.075, 0.05, 0.032)  # semi-axes, m: a 0.15 x 0.10 x 0.064 ellipsoid
PHANTOM_WEDGE = 0.3  # relative change of thickness from the centre to either end
PHANTOM_SUBDIVISIONS = 3  # icosphere level: 642 surface nodes
PHANTOM_MAX_VOLUME = 2e-7  # m^3, tetgen's -a: about 1,600 nodes in all (tetgen's build decides)
PHANTOM_HOLD_CENTRE = (0.0, 1.0, 0.0)  # direction of the hold's centre: the posterior face
PHANTOM_HOLD_RADIUS = 0.03  # m: surface nodes this close to it are the default clamp


def grid_tets(shape: tuple[int, int, int], cell: float) -> tuple[Array, Array]:
    """Nodes and Kuhn-split tets of a box of `shape` hexes with edge `cell`.

    Shape: nodes ((nx+1)(ny+1)(nz+1), 3), tets (6 nx ny nz, 4), every tet positively oriented.
    Node id = (i * (ny+1) + j) * (nz+1) + k for grid index (i, j, k).
    """
    nx, ny, nz = shape
    axes = [np.arange(k + 1) * cell for k in shape]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    idx = np.arange(len(nodes)).reshape(nx + 1, ny + 1, nz + 1)
    bits = np.arange(8)
    corner = np.stack(  # (nx, ny, nz, 8): node id of each hex corner
        [idx[(b & 1) : nx + (b & 1), (b >> 1 & 1) : ny + (b >> 1 & 1), (b >> 2 & 1) : nz + (b >> 2 & 1)] for b in bits],
        axis=-1,
    ).reshape(-1, 8)
    tets = corner[:, KUHN].reshape(-1, 4)
    return nodes, tets.astype(np.int64)


def beam() -> TetMesh:
    """The paper's cantilever: 4 x 4 x 19 hexes of 1 cm, 6 tets each, clamped at x = 0.

    Shape: 500 nodes, 1,824 tets; 0.19 x 0.04 x 0.04 m with the long axis along x.
    """
    nodes, tets = grid_tets((19, 4, 4), 0.01)
    mesh, _ = TetMesh.build(nodes, tets, np.flatnonzero(nodes[:, 0] == 0.0))
    return mesh


def _phantom_radius(d: Array) -> Array:
    """Distance from the centre to the phantom's surface along unit directions d.

    Shape: d (m, 3) -> (m,).
    """
    a = np.asarray(PHANTOM_AXES) * np.ones((len(d), 1))
    a[:, 2] *= 1.0 + PHANTOM_WEDGE * d[:, 0]  # thicker to the right, thinner to the left
    r = 1.0 / np.sqrt(((d / a) ** 2).sum(axis=1))  # the (wedged) ellipsoid's own radius
    bump = np.zeros(len(d))
    for c, amp, w in PHANTOM_BUMPS:  # five bumps, not a loop over points
        c = np.asarray(c) / np.linalg.norm(c)
        bump += amp * np.exp((d @ c - 1.0) / w**2)
    return r * (1.0 + bump)


def phantom_surface(subdivisions: int = PHANTOM_SUBDIVISIONS, relax: int = 100) -> tuple[Array, Array]:
    """The phantom's closed triangulated surface, outward oriented.

    Shape: vertices (v, 3), faces (f, 3).
    The icosphere's vertices are mapped radially onto the surface, then relaxed: each vertex moves
    to its neighbours' centroid and is projected back radially. Why: stretching a sphere to a
    flat ellipsoid makes long thin triangles, and tetgen keeps surface triangles as they are
    (-Y), so their shape bounds the quality of the tets along the boundary.
    """
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    d = np.asarray(sphere.vertices, np.float64)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    faces = np.asarray(sphere.faces, np.int64)
    edges = np.asarray(sphere.edges_unique, np.int64)
    n = len(d)
    adj = sp.coo_matrix((np.ones(2 * len(edges)), (edges.ravel(), edges[:, ::-1].ravel())), (n, n))
    adj = sp.diags(1.0 / np.asarray(adj.sum(axis=1)).ravel()) @ adj.tocsr()
    for _ in range(relax):  # fixed-point iterations, vectorised over vertices
        x = d * _phantom_radius(d)[:, None]
        c = adj @ x
        d = c / np.linalg.norm(c, axis=1, keepdims=True)
    x = d * _phantom_radius(d)[:, None]
    return x, faces


def phantom() -> TetMesh:
    """An organ-like phantom: a lobed, wedged, flattened ellipsoid, 0.17 x 0.10 x 0.08 m.

    Shape: about 1,600 nodes (the first 642 are the surface), about 7,900 tets, 50 fixed: the
    interior depends on tetgen's build (1,620 nodes and 7,827 tets for the shipped entry, 1,636
    and 7,931 on another machine), the surface and the clamp do not.
    The default clamp is the surface nodes within 3 cm of the posterior pole (+y), about 8% of
    the surface: like a liver's ligaments, a hold on its back that leaves both lobes free to
    bend and the front to be pushed (1 N moves it by 2 to 6 cm).
    """
    from .meshfile import tetrahedralise

    vertices, faces = phantom_surface()
    nodes, tets = tetrahedralise(vertices, faces, max_volume=PHANTOM_MAX_VOLUME)
    # the surface vertices come out first and unchanged (tetgen -Y), so the hold is chosen on them
    d = np.asarray([PHANTOM_HOLD_CENTRE], np.float64)
    anchor = (d * _phantom_radius(d)[:, None])[0]
    held = np.flatnonzero(np.linalg.norm(vertices - anchor, axis=1) <= PHANTOM_HOLD_RADIUS)
    mesh, _ = TetMesh.build(nodes, tets, held)  # tetgen uses every node: no renumbering
    log.debug("phantom: %d nodes, %d tets, %d held", mesh.n_nodes, mesh.n_tets, mesh.fixed.size)
    return mesh

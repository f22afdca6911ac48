"""Tetrahedral meshes: nodes, P1 tets, fixed nodes, and the facts derived from them.

A :class:`TetMesh` is a thin frozen object over three arrays; every derived fact (volumes,
shape-function gradients, the outward boundary, surface neighbourhoods) is a cached property,
computed on first use and returned read-only, as trimesh does.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
from functools import cached_property

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

log = logging.getLogger(__name__)

Array = np.ndarray

#: Local faces of a positively oriented tet (det[b-a, c-a, d-a] > 0), each ordered so that its
#: right-hand normal points out of the tet.
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


class MeshError(ValueError):
    """A mesh that cannot be used, with a message that says why."""


def _readonly(a: Array) -> Array:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


#: a tet's six edges as local vertex pairs: the order its edge midpoints are numbered in
TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])


def edge_midpoints(n_nodes: int, tets: Array) -> tuple[Array, Array]:
    """The tets' edges (e, 2), sorted, and each tet's six midpoint ids n + edge index in
    TET_EDGES' order (t, 6): a subdivided mesh's numbering, and a ten-node tet's."""
    pairs = np.sort(tets[:, TET_EDGES], axis=2).reshape(-1, 2)  # (6 t, 2)
    edges, inverse = np.unique(pairs, axis=0, return_inverse=True)
    return edges, n_nodes + inverse.reshape(-1, 6)


def signed_volumes(nodes: Array, tets: Array) -> Array:
    """Signed volume of each tet.

    Shape: nodes (n, 3), tets (t, 4) -> (t,).
    """
    x = nodes[tets]
    return np.linalg.det(x[:, 1:] - x[:, :1]) / 6.0


def components(n_nodes: int, tets: Array) -> Array:
    """Connected-component label of every node, through shared tets (unused nodes: -1)."""
    rows = np.repeat(tets[:, 0], 3)
    cols = tets[:, 1:].ravel()
    graph = sp.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(n_nodes, n_nodes))
    _, labels = csgraph.connected_components(graph, directed=False)
    used = np.zeros(n_nodes, bool)
    used[tets.ravel()] = True
    return np.where(used, labels, -1)


FaceTable = tuple[Array, Array, Array]


def face_table(tets: Array) -> FaceTable:
    """The tets' faces as TET_FACES orders them (4 t, 3), each one's index among the distinct
    faces (4 t,), and how many tets share each distinct face."""
    faces = tets[:, TET_FACES].reshape(-1, 3)
    _, inverse, counts = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True, return_counts=True)
    return faces, inverse.ravel(), counts


def face_components(tets: Array, table: FaceTable | None = None) -> int:
    """How many parts the tets make when joined only through shared faces. Raises MeshError for
    a face that more than two tets share."""
    _, inverse, counts = face_table(tets) if table is None else table
    if counts.max() > 2:
        raise MeshError(f"{int((counts > 2).sum())} faces belong to more than two tets (overlapping or repeated tets)")
    order = np.argsort(inverse, kind="stable")
    owner, face = order // 4, inverse[order]
    pair = np.flatnonzero(face[1:] == face[:-1])  # the two tets of each interior face, side by side
    n = len(tets)
    graph = sp.coo_matrix((np.ones(pair.size), (owner[pair], owner[pair + 1])), shape=(n, n))
    return int(csgraph.connected_components(graph, directed=False)[0])


def folded_faces(nodes: Array, tets: Array, table: FaceTable | None = None) -> tuple[int, float]:
    """Interior faces whose two (positively oriented) tets lie on the same side of it, and how far
    the tets' total volume exceeds the volume their boundary encloses (relative). A mesh whose tets
    only had mixed vertex orders has none once oriented; a tangled one (a node pushed through a
    face) has some, and its tets overlap: the FEM would count the overlap twice."""
    faces, inverse, counts = face_table(tets) if table is None else table
    # a face's orientation: the parity of the permutation that sorts it; the two tets of an interior
    # face see it in opposite orientations exactly when they lie on its two sides
    parity = ((faces[:, 0] > faces[:, 1]) ^ (faces[:, 0] > faces[:, 2]) ^ (faces[:, 1] > faces[:, 2])).astype(np.int64)
    shares = counts[inverse]
    odd = np.bincount(inverse[shares == 2], weights=parity[shares == 2], minlength=counts.size)  # 0 or 2: one side
    folded = int(((counts == 2) & (odd != 1)).sum())
    x = nodes[faces[shares == 1]]
    enclosed = np.einsum("ij,ij->i", x[:, 0], np.cross(x[:, 1], x[:, 2])).sum() / 6.0  # divergence theorem
    total = signed_volumes(nodes, tets).sum()
    return folded, float(total / enclosed - 1.0) if enclosed > 0 else float("inf")


#: nodes closer than this share of the mesh's bounding-box diagonal count as one point: far
#: below any element (a 100k-tet organ's smallest edge is ~1e-3 of it), far above round-off
COINCIDENT_TOL = 1e-9


def coincident_nodes(nodes: Array, tets: Array) -> None:
    """Refuse tets on nodes that coincide (a file whose shared nodes were not merged).

    Why refuse, not merge: the copies cut the body along their faces (a slit whose faces become
    surface, loads and all) or into parts, and merging would renumber the nodes a scene's ids
    name. Nodes no tet uses are dropped later, coincident or not.
    """
    points = nodes[np.unique(tets)]
    span = float(np.linalg.norm(np.ptp(points, axis=0))) or 1.0
    # pairs within the distance, not cells of a rounded grid: two copies astride a cell's edge
    # fell in different cells and passed
    pairs = cKDTree(points).query_pairs(span * COINCIDENT_TOL, output_type="ndarray")
    extra = int(np.unique(pairs.max(axis=1)).size) if len(pairs) else 0
    if extra:
        at = points[pairs[0, 0]]
        raise MeshError(
            f"{extra} nodes used by tets coincide with another node (within {COINCIDENT_TOL:g} x the mesh's size; "
            f"first at {at.tolist()}): the mesh's nodes were not merged, so it is cut along them; merge coincident "
            "nodes (gmsh: Coherence Mesh; meshio/trimesh: merge_vertices) and load it again"
        )


@dataclasses.dataclass(frozen=True, eq=False)
class TetMesh:
    """A P1 tetrahedral mesh with its Dirichlet nodes.

    Shape: nodes (n, 3) float64, tets (t, 4) int64 positively oriented, fixed (f,) int64 sorted.
    Build one with :func:`TetMesh.build` (which validates and repairs); the constructor trusts
    its arguments.
    """

    nodes: Array
    tets: Array
    fixed: Array = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))

    def __post_init__(self) -> None:
        object.__setattr__(self, "nodes", _readonly(np.asarray(self.nodes, np.float64)))
        object.__setattr__(self, "tets", _readonly(np.asarray(self.tets, np.int64)))
        object.__setattr__(self, "fixed", _readonly(np.unique(np.asarray(self.fixed, np.int64))))

    # -- construction -------------------------------------------------------------------------

    @classmethod
    def build(
        cls,
        nodes: Array,
        tets: Array,
        fixed: Array | None = None,
        *,
        rel_volume_tol: float = 1e-9,
    ) -> tuple[TetMesh, Array | None]:
        """Validate and repair raw arrays into a mesh.

        Inverted tets are re-oriented (logged): a mesh whose tets only mix their vertex orders;
        tets on coincident nodes (unmerged copies: :func:`coincident_nodes`), a tangled mesh
        (re-oriented, some tets overlap: a node moved through a face), degenerate tets, several
        components (by nodes, or by faces: parts touching at an edge or a point) and bad indices
        are refused with a :class:`MeshError`; unused nodes are dropped, in which case
        the second value maps each kept node to its index in the input (else it is None).
        """
        nodes = np.asarray(nodes, np.float64)
        tets = np.asarray(tets)
        if nodes.ndim != 2 or nodes.shape[1] != 3 or len(nodes) == 0:
            raise MeshError(f"nodes must be a non-empty (n, 3) array, got shape {nodes.shape}")
        if not np.isfinite(nodes).all():
            raise MeshError("nodes contain NaN or infinite coordinates")
        if tets.ndim != 2 or tets.shape[1] != 4 or len(tets) == 0:
            raise MeshError(f"tets must be a non-empty (t, 4) array, got shape {tets.shape}")
        if not np.issubdtype(tets.dtype, np.integer):
            raise MeshError("tets must hold integer node ids")
        tets = tets.astype(np.int64)
        if tets.min() < 0 or tets.max() >= len(nodes):
            raise MeshError(f"tets refer to node ids outside 0..{len(nodes) - 1}")
        if (np.sort(tets, axis=1)[:, 1:] == np.sort(tets, axis=1)[:, :-1]).any():
            raise MeshError("some tets repeat a node")
        coincident_nodes(nodes, tets)

        vol = signed_volumes(nodes, tets)
        scale = np.median(np.abs(vol))
        bad = np.abs(vol) <= rel_volume_tol * scale
        if bad.any():
            raise MeshError(
                f"{int(bad.sum())} degenerate tets (|volume| <= {rel_volume_tol:g} x median), "
                f"first at index {int(np.flatnonzero(bad)[0])}"
            )
        inverted = vol < 0
        if inverted.any():
            log.warning("re-oriented %d inverted tets", int(inverted.sum()))
            tets = tets.copy()
            tets[inverted, 2], tets[inverted, 3] = tets[inverted, 3], tets[inverted, 2].copy()

        labels = components(len(nodes), tets)
        sizes = np.unique(labels[labels >= 0], return_counts=True)[1]  # used nodes only: no empty components
        if sizes.size > 1:
            largest = sorted(sizes.tolist(), reverse=True)[:5]
            raise MeshError(
                f"the mesh has {sizes.size} separate components (node counts {largest}); "
                "split it into one scene per body"
            )

        table = face_table(tets)  # sorted once: both checks below read it
        parts = face_components(tets, table)
        if parts > 1:  # one body by its nodes, several by its faces: they touch at edges or points
            raise MeshError(
                f"the mesh is {parts} parts that touch only along an edge or at a point (no shared face): "
                "it could turn about the contact, so it is not one body; mesh the contact as a solid or split it"
            )
        folded, excess = folded_faces(nodes, tets, table)
        if folded:  # re-orienting made each tet positive, not the mesh untangled
            raise MeshError(
                f"the mesh is tangled: {folded} interior faces have both their tets on one side, so tets overlap "
                f"(their volumes add up to {1 + excess:.4g} x the volume the boundary encloses), as where a node "
                "was moved through a face; re-orienting its tets cannot fix that: fix the mesh"
            )

        fixed = np.zeros(0, np.int64) if fixed is None else np.asarray(fixed, np.int64)
        if fixed.size and (fixed.min() < 0 or fixed.max() >= len(nodes)):
            raise MeshError(f"fixed node ids must lie in 0..{len(nodes) - 1}")

        kept: Array | None = None
        used = labels >= 0
        if not used.all():
            log.warning("dropped %d nodes that no tet uses (node ids renumbered)", int((~used).sum()))
            kept = np.flatnonzero(used)
            new_id = np.full(len(nodes), -1, np.int64)
            new_id[kept] = np.arange(kept.size)
            nodes, tets = nodes[kept], new_id[tets]
            fixed = new_id[fixed]
            fixed = fixed[fixed >= 0]
        return cls(nodes, tets, fixed), kept

    def with_fixed(self, fixed: Array) -> TetMesh:
        """The same mesh with other Dirichlet nodes (cached facts are recomputed)."""
        return TetMesh(self.nodes, self.tets, fixed)

    def scaled(self, factor: float) -> TetMesh:
        return TetMesh(self.nodes * factor, self.tets, self.fixed)

    # -- sizes --------------------------------------------------------------------------------

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    @cached_property
    def hash(self) -> str:
        """Content hash of nodes, tets and fixed nodes (the model store's identity check)."""
        h = hashlib.sha256()
        for a in (self.nodes, self.tets, self.fixed):
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()

    # -- geometry -----------------------------------------------------------------------------

    @cached_property
    def volumes(self) -> Array:
        """Shape: (t,). Positive by construction."""
        return _readonly(signed_volumes(self.nodes, self.tets))

    @cached_property
    def spacing(self) -> float:
        """The nodes' spacing (m): the cube root of the tets' mean volume."""
        return float(np.cbrt(np.mean(np.abs(self.volumes))))

    @cached_property
    def shape_gradients(self) -> Array:
        """Gradients of the four P1 shape functions in each tet, in the reference frame.

        Shape: (t, 4, 3); row a is grad N_a, constant over the tet.
        """
        x = self.nodes[self.tets]
        D = np.transpose(x[:, 1:] - x[:, :1], (0, 2, 1))  # columns b-a, c-a, d-a
        Dinv = np.linalg.inv(D)  # rows: grads of N_1..N_3
        grads = np.empty((self.n_tets, 4, 3))
        grads[:, 1:] = Dinv
        grads[:, 0] = -Dinv.sum(axis=1)
        return _readonly(grads)

    @cached_property
    def lumped_areas(self) -> Array:
        """Boundary area attributed to each node (a third of each adjacent face). Shape: (n,)."""
        area = np.zeros(self.n_nodes)
        np.add.at(area, self.surface_faces.ravel(), np.repeat(self.face_areas / 3.0, 3))
        return _readonly(area)

    @cached_property
    def face_areas(self) -> Array:
        x = self.nodes[self.surface_faces]
        return _readonly(0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1))

    @cached_property
    def face_normals(self) -> Array:
        """Unit outward normals of the boundary faces. Shape: (f, 3)."""
        x = self.nodes[self.surface_faces]
        n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
        return _readonly(n / np.linalg.norm(n, axis=1, keepdims=True))

    @cached_property
    def vertex_normals(self) -> Array:
        """Area-weighted outward normals at nodes (zero for interior nodes). Shape: (n, 3)."""
        x = self.nodes[self.surface_faces]
        n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
        acc = np.zeros((self.n_nodes, 3))
        for k in range(3):  # three corners, not a loop over faces
            np.add.at(acc, self.surface_faces[:, k], n)
        norm = np.linalg.norm(acc, axis=1, keepdims=True)
        return _readonly(np.divide(acc, norm, out=np.zeros_like(acc), where=norm > 0))

    def patch_normal(self, nodes: Array) -> Array:
        """The unit outward normal of a surface patch: its nodes' area-weighted normals summed
        (the direction a grasper pulls it). Shape: (k,) -> (3,)."""
        n = self.vertex_normals[np.asarray(nodes, np.int64)].sum(axis=0)
        return n / np.linalg.norm(n)

    @property
    def bounding_box(self) -> Array:
        return np.stack([self.nodes.min(0), self.nodes.max(0)])

    @property
    def size(self) -> float:
        """Length of the bounding-box diagonal: the mesh's natural length scale."""
        return float(np.linalg.norm(np.ptp(self.nodes, axis=0)))

    # -- topology -----------------------------------------------------------------------------

    @cached_property
    def surface_faces(self) -> Array:
        """Boundary triangles, outward oriented. Shape: (f, 3)."""
        faces = self.tets[:, TET_FACES].reshape(-1, 3)
        key = np.sort(faces, axis=1)
        _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        once = counts[inverse.ravel()] == 1
        if (counts > 2).any():
            raise MeshError(f"{int((counts > 2).sum())} faces are shared by more than two tets")
        return _readonly(faces[once])

    @cached_property
    def surface_nodes(self) -> Array:
        """Sorted ids of the nodes on the boundary. Shape: (s,)."""
        return _readonly(np.unique(self.surface_faces))

    @cached_property
    def free_mask(self) -> Array:
        mask = np.ones(self.n_nodes, bool)
        mask[self.fixed] = False
        return _readonly(mask)

    @cached_property
    def free_surface_nodes(self) -> Array:
        """Boundary nodes that are not fixed: where surface forces may act by default."""
        return _readonly(self.surface_nodes[self.free_mask[self.surface_nodes]])

    @cached_property
    def surface_graph(self) -> sp.csr_matrix:
        """Boundary edges weighted by length, over all n nodes (interior rows empty)."""
        f = self.surface_faces
        i = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
        j = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
        w = np.linalg.norm(self.nodes[i] - self.nodes[j], axis=1)
        g = sp.coo_matrix((w, (i, j)), shape=(self.n_nodes, self.n_nodes)).tocsr()
        g = g.maximum(g.T)  # each edge once in each direction, its length (not a sum)
        return g

    def surface_pieces(self, nodes: Array) -> tuple[sp.csr_matrix, Array]:
        """The surface graph with only the edges between two of `nodes` (surface node ids), and
        the piece of each of them: the connected parts they form along the surface. Shape: (n, n),
        (k,) labels 0.. in the order of `nodes`."""
        keep = np.zeros(self.n_nodes, bool)
        keep[nodes] = True
        mask = sp.diags(keep.astype(np.float64))
        graph = (mask @ self.surface_graph @ mask).tocsr()
        graph.eliminate_zeros()
        _, labels = csgraph.connected_components(graph[nodes][:, nodes], directed=False)
        return graph, labels

    def surface_patch(self, centre: int, size: int) -> Array:
        """The `size` free surface nodes nearest to `centre` along the surface (geodesic).

        Why geodesic: on a thin part (a beam's corner, a liver lobe) the Euclidean neighbours
        can lie on the opposite face, which no tool touches at once.
        """
        dist = csgraph.dijkstra(self.surface_graph, indices=int(centre), limit=np.inf)
        cand = self.free_surface_nodes
        order = np.argsort(dist[cand], kind="stable")
        return cand[order[:size]]

    def nodes_in_box(self, lo: Array, hi: Array) -> Array:
        """Ids of nodes inside the closed box [lo, hi]."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        return np.flatnonzero(((self.nodes >= lo) & (self.nodes <= hi)).all(axis=1))

    # -- degrees of freedom -------------------------------------------------------------------

    @cached_property
    def free_dofs(self) -> Array:
        """Flat indices (3 * node + axis) of the unknowns. Shape: (3 * n_free,)."""
        return _readonly(np.flatnonzero(np.repeat(self.free_mask, 3)))

    def pack(self, u: Array) -> Array:
        """(n, 3) -> free dofs (3 n_free,)."""
        return np.asarray(u).reshape(-1)[self.free_dofs]

    def unpack(self, x: Array) -> Array:
        """Free dofs (3 n_free,) -> (n, 3) with zeros on fixed nodes."""
        u = np.zeros(3 * self.n_nodes)
        u[self.free_dofs] = x
        return u.reshape(-1, 3)

    def summary(self) -> dict:
        return {
            "n_nodes": self.n_nodes,
            "n_tets": self.n_tets,
            "n_surface_nodes": int(self.surface_nodes.size),
            "n_surface_faces": int(len(self.surface_faces)),
            "n_fixed": int(self.fixed.size),
            "bounding_box": self.bounding_box.tolist(),
            "volume": float(self.volumes.sum()),
        }

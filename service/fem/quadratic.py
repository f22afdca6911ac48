"""Ten-node (quadratic) tets: the same Neo-Hookean energy on quadratic elements of a mesh.

The method runs on linear tets (SCENES.md). Under a tool's load on the paper's liver those are
far stiffer than the converged solution, and the mesh subdivided once is still well short of it;
quadratic tets on the scene's own mesh, with as many nodes as that subdivision, come nearer
than the mesh subdivided twice (docs/performance.md, "Quadratic tets"). So the benchmarks'
truth may use them. Their nodes are a subdivided mesh's (`nodes`: the corners keep their ids,
edge midpoints follow, its fixed set), so loads, clouds and displacements read as on that mesh.
Straight-sided elements and the four-point rule, exact for the small-strain stiffness.
"""

from __future__ import annotations

import dataclasses
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from ..mesh import TET_EDGES, TetMesh, edge_midpoints
from .assembly import csr_pattern, neo_hookean_element_stiffness
from .material import NeoHookean
from .model import FEMModel, FEMOperator

Array = np.ndarray

#: the four-point degree-2 rule's barycentric coordinates (q, 4); each point weighs vol / 4
_QA, _QB = 0.5854101966249685, 0.1381966011250105
BARYCENTRIC = np.full((4, 4), _QB) + np.eye(4) * (_QA - _QB)


def quadratic_gradients(elements: TetMesh) -> Array:
    """The ten shape functions' gradients at each quadrature point: corner a, L_a (2 L_a - 1);
    edge (a, b) in TET_EDGES' order, 4 L_a L_b; grad L are the linear tet's. Shape: (q, t, 10, 3)."""
    dNdL = np.zeros((4, 10, 4))
    for a in range(4):
        dNdL[:, a, a] = 4 * BARYCENTRIC[:, a] - 1
    for e, (a, b) in enumerate(TET_EDGES):
        dNdL[:, 4 + e, a] = 4 * BARYCENTRIC[:, b]
        dNdL[:, 4 + e, b] = 4 * BARYCENTRIC[:, a]
    return np.ascontiguousarray(np.einsum("qak,tkx->qtax", dNdL, elements.shape_gradients))


@dataclasses.dataclass(frozen=True, eq=False)
class QuadraticAssembler:
    """Energy, forces and tangent on ten-node tets: `elements` gives the corners, `nodes` (the
    elements' mesh subdivided once: truth.subdivide) every node and the fixed ones. The
    Assembler's interface; u given on all of `nodes`, shape (n, 3)."""

    elements: TetMesh
    nodes: TetMesh
    material: NeoHookean
    tets: Array = dataclasses.field(init=False, repr=False)

    def __post_init__(self) -> None:
        edges, mid = edge_midpoints(self.elements.n_nodes, self.elements.tets)
        if self.nodes.n_nodes != self.elements.n_nodes + len(edges):
            raise ValueError("`nodes` must be `elements` subdivided once: corners, then edge midpoints")
        # corner ids, then midpoint ids in TET_EDGES' order (t, 10)
        object.__setattr__(self, "tets", np.ascontiguousarray(np.hstack([self.elements.tets, mid])))

    @cached_property
    def _grads(self) -> Array:
        return quadratic_gradients(self.elements)

    @cached_property
    def _weights(self) -> Array:
        return self.elements.volumes / 4.0

    @cached_property
    def _pattern(self) -> tuple[Array, Array, Array, Array]:
        return csr_pattern(self.tets, self.nodes.free_dofs, self.nodes.n_nodes)

    @property
    def spacing(self) -> float:
        """The nodes' spacing (m): that of `nodes`' tets (TetMesh.spacing), half an element's size."""
        return self.nodes.spacing

    @property
    def n_free(self) -> int:
        return int(self.nodes.free_dofs.size)

    def with_material(self, material: NeoHookean) -> QuadraticAssembler:
        return QuadraticAssembler(self.elements, self.nodes, material)

    def _F_at(self, u: Array, q: int) -> Array:
        F = np.matmul(np.asarray(u)[self.tets].transpose(0, 2, 1), self._grads[q])  # (t, 3, 3)
        F[:, [0, 1, 2], [0, 1, 2]] += 1.0
        return F

    def F(self, u: Array) -> Array:
        """F = I + grad u at every quadrature point. Shape: (4 t, 3, 3)."""
        return np.concatenate([self._F_at(u, q) for q in range(4)])

    def energy(self, u: Array) -> float:
        """sum over tets and points of w W(F); +inf if F inverts anywhere."""
        return float(sum(self._weights @ self.material.energy(self._F_at(u, q)) for q in range(4)))

    def internal_force(self, u: Array) -> Array:
        """dE/du at every node. Shape: (n, 3)."""
        fe = np.zeros((len(self.tets), 10, 3))
        for q in range(4):
            P = self.material.stress(self._F_at(u, q)) * self._weights[:, None, None]
            fe += np.matmul(self._grads[q], P.transpose(0, 2, 1))  # w P grad N_a
        idx, n = self.tets.ravel(), self.nodes.n_nodes
        flat = fe.reshape(-1, 3)
        return np.stack([np.bincount(idx, weights=flat[:, i], minlength=n) for i in range(3)], axis=1)

    def tangent(self, u: Array) -> sp.csr_matrix:
        """Tangent stiffness over the free dofs, symmetric. Shape: (3 n_free, 3 n_free)."""
        keep, slot, indptr, indices = self._pattern
        Ke = sum(
            neo_hookean_element_stiffness(self.material, self._F_at(u, q), self._grads[q], self._weights)
            for q in range(4)
        )
        data = np.bincount(slot, weights=np.asarray(Ke).reshape(-1)[keep], minlength=indices.size)
        return sp.csr_matrix((data, indices, indptr), shape=(self.n_free, self.n_free))

    def stiffness_at_rest(self) -> sp.csr_matrix:
        return self.tangent(np.zeros((self.nodes.n_nodes, 3)))

    def pack(self, u: Array) -> Array:
        return self.nodes.pack(u)

    def unpack(self, x: Array) -> Array:
        return self.nodes.unpack(x)


@dataclasses.dataclass(frozen=True, eq=False)
class QuadraticFEM(FEMModel):
    """The Neo-Hookean FEM on ten-node tets: equilibria for a truth, not a registration's
    forward model (its rest state and Jacobians would be the linear tets'). `mesh` is the
    node mesh (`elements` subdivided once)."""

    elements: TetMesh | None = None

    @cached_property
    def assembler(self) -> QuadraticAssembler:  # type: ignore[override]
        if self.elements is None:
            raise ValueError("QuadraticFEM needs `elements`, the mesh whose tets carry the ten nodes")
        return QuadraticAssembler(self.elements, self.mesh, self.material)

    def with_stiffness(self, E: float) -> QuadraticFEM:
        return dataclasses.replace(self, material=self.material.with_stiffness(E))

    def restrict(self, support: Array, nodes: Array | None = None) -> FEMOperator:
        return _Equilibria(self, support, nodes)


class _Equilibria(FEMOperator):
    """A quadratic model's operator: displacements only."""

    def _rest_solver(self):
        raise NotImplementedError("quadratic tets give equilibria only: registration runs on linear tets")

    def __call__(self, g: Array):
        raise NotImplementedError("quadratic tets give equilibria only: registration runs on linear tets")

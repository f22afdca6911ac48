"""Vectorised P1 assembly of energy, internal forces and tangent stiffness over all tets at once.

The sparsity of the tangent never changes, so :class:`Assembler` computes once where each of the
t x 12 x 12 element entries lands in the CSR data array of the free-dof matrix; assembling is
then one weighted ``bincount``. Fixed dofs are eliminated (their rows and columns dropped), so
the matrix handed to the factorisation is the reduced one.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from functools import cached_property
from typing import TypeVar

import numpy as np
import scipy.sparse as sp

from ..mesh import TetMesh
from ..spare import Beside, helping
from .kernels import compiled as _kernels
from .material import NeoHookean, det3, inv_transpose

Array = np.ndarray
T = TypeVar("T")

#: tets from which a frame's assembly hands half to a spare core: a handoff costs about 50 us,
#: the liver's 10,703 tets' tangent 2.3 ms on one core and 1.35 on two (docs/performance.md)
BESIDE_MIN_TETS = 4000


def deformation_gradient(u: Array, tets: Array, grads: Array) -> Array:
    """F = I + grad u per tet. Shape: u (n, 3), tets (t, 4), grads (t, 4, 3) -> (t, 3, 3)."""
    F = np.matmul(u[tets].transpose(0, 2, 1), grads)  # sum_a u_a (x) grad N_a
    F[:, 0, 0] += 1.0
    F[:, 1, 1] += 1.0
    F[:, 2, 2] += 1.0
    return F


def neo_hookean_element_stiffness(mat: NeoHookean, F: Array, grads: Array, vol: Array) -> Array:
    """Element tangents K_e[t, a, i, b, k] for the Neo-Hookean law, from its tangent's structure.

    With v_a = F^-T grad N_a (spatial gradients) and c = mu - lam ln J, contracting dP/dF with
    the shape gradients gives  vol [mu (gN_a . gN_b) d_ik + lam v_ai v_bk + c v_ak v_bi],
    a few broadcast products instead of the generic (t, 81) x (t, 16) contraction (3x faster;
    tests check both agree). Shape: F (t, 3, 3), grads (t, a, 3), vol (t,) -> (t, a, 3, a, 3).
    """
    J = det3(F)
    v = np.matmul(grads, inv_transpose(F, J).transpose(0, 2, 1))  # v[t,a,i] = F^-T_iJ gN_aJ
    lam_v = v * (mat.lam * vol)[:, None, None]
    c_v = v * ((mat.mu - mat.lam * np.log(J)) * vol)[:, None, None]
    a = grads.shape[1]  # shape functions: 4 on a linear tet, 10 on a quadratic one
    K = np.empty((len(F), a, 3, a, 3))
    np.multiply(lam_v[:, :, :, None, None], v[:, None, None, :, :], out=K)
    K += c_v[:, :, None, None, :] * v.transpose(0, 2, 1)[:, None, :, :, None]
    gram = np.matmul(grads, grads.transpose(0, 2, 1)) * (mat.mu * vol)[:, None, None]
    for i in range(3):  # the mu (gN_a . gN_b) identity block, one axis at a time
        K[:, :, i, :, i] += gram
    return K


def generic_element_stiffness(A: Array, grads: Array, vol: Array) -> Array:
    """K_e[t,a,i,b,k] = vol sum_JL A[t,i,J,k,L] gN[t,a,J] gN[t,b,L] for any law's tangent A."""
    tmp = np.einsum("tiJkL,tbL->tiJbk", A, grads)
    return np.einsum("taJ,tiJbk->taibk", grads, tmp) * vol[:, None, None, None, None]


def csr_pattern(elements: Array, free_dofs: Array, n_nodes: int) -> tuple[Array, Array, Array, Array]:
    """Where element matrices land in the free-dof CSR matrix: (keep mask over the t * d^2
    entries, CSR data slot of each kept entry, indptr, indices), d = 3 x nodes per element."""
    reduced = np.full(3 * n_nodes, -1, np.int64)
    reduced[free_dofs] = np.arange(free_dofs.size)
    d = 3 * elements.shape[1]
    edofs = reduced[(3 * elements[:, :, None] + np.arange(3)).reshape(-1, d)]  # (t, d)
    rows = np.repeat(edofs, d, axis=1).ravel()
    cols = np.tile(edofs, (1, d)).ravel()
    keep = (rows >= 0) & (cols >= 0)
    nf = free_dofs.size
    key = rows[keep] * nf + cols[keep]
    uniq, slot = np.unique(key, return_inverse=True)
    r, c = np.divmod(uniq, nf)
    indptr = np.searchsorted(r, np.arange(nf + 1))
    return keep, slot.ravel(), indptr, c


@dataclasses.dataclass(frozen=True, eq=False)
class Assembler:
    """Energy, forces and tangent of a mesh under one material, with u given on all nodes.

    Shape: u (n, 3) everywhere; the tangent is over the free dofs, (3 n_free, 3 n_free).
    `compiled` picks the numba kernels (default where available) or the NumPy reference.
    """

    mesh: TetMesh
    material: NeoHookean
    compiled: bool = dataclasses.field(default_factory=lambda: _kernels() is not None)

    def with_material(self, material: NeoHookean) -> Assembler:
        """Same mesh and precomputed pattern, another material (the pattern is shared)."""
        new = Assembler(self.mesh, material, self.compiled)
        for name in ("_pattern", "_slots"):
            if name in self.__dict__:
                new.__dict__[name] = self.__dict__[name]
        return new

    @property
    def n_free(self) -> int:
        return int(self.mesh.free_dofs.size)

    @property
    def spacing(self) -> float:
        """The nodes' spacing (m): the mesh's (TetMesh.spacing)."""
        return self.mesh.spacing

    def F(self, u: Array) -> Array:
        return deformation_gradient(u, self.mesh.tets, self.mesh.shape_gradients)

    def _args(self, u: Array) -> tuple:
        m = self.mesh
        return (np.ascontiguousarray(u, np.float64), m.tets, m.shape_gradients, m.volumes,
                self.material.mu, self.material.lam)  # fmt: skip

    @cached_property
    def _halves(self) -> tuple[tuple[Array, Array, Array, Array], ...]:
        """The tets in two halves, each (tets, grads, vol, CSR slots) as views."""
        m, h = self.mesh, len(self.mesh.tets) // 2
        return tuple((m.tets[a:b], m.shape_gradients[a:b], m.volumes[a:b], self._slots[144 * a : 144 * b])
                     for a, b in ((0, h), (h, len(m.tets))))  # fmt: skip

    def _in_halves(self, run: Callable[[tuple], T]) -> tuple[T, T]:
        """`run` over each half of the tets: the second on a spare core where a frame's caller has
        one (spare.helping) and the mesh is worth it, else inline. The compiled kernels always
        sum the two halves, so an answer's digits do not depend on the server's load."""
        first, second = self._halves
        beside = len(self.mesh.tets) >= BESIDE_MIN_TETS and helping()
        other = Beside(functools.partial(run, second), start=beside)
        return run(first), other.result()

    def energy(self, u: Array) -> float:
        """Stored elastic energy sum_e vol_e W(F_e); +inf if any tet is inverted."""
        if self.compiled:
            return float(_kernels().energy(*self._args(u)))
        return float(self.mesh.volumes @ self.material.energy(self.F(u)))

    def internal_force(self, u: Array, F: Array | None = None) -> Array:
        """dE/du at every node. Shape: (n, 3)."""
        if self.compiled and F is None:
            u, *_, mu, lam = self._args(u)

            def half(h: tuple) -> Array:
                out = np.empty((self.mesh.n_nodes, 3))
                _kernels().internal_force(u, *h[:3], mu, lam, out)
                return out

            a, b = self._in_halves(half)
            a += b
            return a
        F = self.F(u) if F is None else F
        P = self.material.stress(F) * self.mesh.volumes[:, None, None]
        fe = np.matmul(self.mesh.shape_gradients, P.transpose(0, 2, 1))  # vol P grad N_a
        return self._scatter(fe)

    def _scatter(self, fe: Array) -> Array:
        """Sum per-tet nodal vectors (t, 4, 3) into nodes (n, 3)."""
        idx = self.mesh.tets.ravel()
        n = self.mesh.n_nodes
        fe = fe.reshape(-1, 3)
        return np.stack([np.bincount(idx, weights=fe[:, i], minlength=n) for i in range(3)], axis=1)

    def element_stiffness(self, F: Array) -> Array:
        return neo_hookean_element_stiffness(self.material, F, self.mesh.shape_gradients, self.mesh.volumes)

    @cached_property
    def _pattern(self) -> tuple[Array, Array, Array, Array]:
        return csr_pattern(self.mesh.tets, self.mesh.free_dofs, self.mesh.n_nodes)

    @cached_property
    def _slots(self) -> Array:
        """CSR slot of every element entry (t * 144,), -1 where a dof is fixed."""
        keep, slot, _, _ = self._pattern
        full = np.full(keep.size, -1, np.int64)
        full[keep] = slot
        return full

    def tangent(self, u: Array, F: Array | None = None) -> sp.csr_matrix:
        """Tangent stiffness over the free dofs, symmetric. Shape: (3 n_free, 3 n_free)."""
        _, _, indptr, indices = self._pattern
        nf = self.n_free
        if self.compiled and F is None:
            u, *_, mu, lam = self._args(u)

            def half(h: tuple) -> Array:
                out = np.empty(indices.size)
                _kernels().tangent_data(u, *h[:3], mu, lam, h[3], out)
                return out

            data, other = self._in_halves(half)
            data += other
        else:
            F = self.F(u) if F is None else F
            Ke = self.element_stiffness(F).reshape(-1)
            keep, slot, _, _ = self._pattern
            data = np.bincount(slot, weights=Ke[keep], minlength=indices.size)
        return sp.csr_matrix((data, indices, indptr), shape=(nf, nf))

    def stiffness_at_rest(self) -> sp.csr_matrix:
        """The small-strain (linear elasticity) stiffness: the tangent at u = 0."""
        return self.tangent(np.zeros((self.mesh.n_nodes, 3)))

    # -- free-dof packing ---------------------------------------------------------------------

    def pack(self, u: Array) -> Array:
        """(n, 3) -> free dofs (3 n_free,): TetMesh.pack."""
        return self.mesh.pack(u)

    def unpack(self, x: Array) -> Array:
        """Free dofs (3 n_free,) -> (n, 3) with zeros on fixed nodes: TetMesh.unpack."""
        return self.mesh.unpack(x)

"""The rest compliance: the small-strain (linear) response K0^-1 of one mesh and material.

Exact linear physics holds at any load site: one factorisation of the rest stiffness, then one
back-substitution per loaded degree of freedom. The physics surrogate adds it outside its
basis, and its network reads it (surrogate/network.py); the FEM's rest state and the error
estimate solve with it too. One factorisation per mesh, material and backend serves every
model and session on it.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable

import numpy as np

from ..mesh import TetMesh
from .assembly import Assembler
from .linsolve import make_solver
from .material import NeoHookean

Array = np.ndarray

#: factorisations kept, least recently used dropped: a few meshes per server
_KEEP = 8
_cache: OrderedDict[tuple, RestCompliance] = OrderedDict()
_cache_lock = threading.Lock()


class RestCompliance:
    """K0^-1 on full-length (node-major, 3n) vectors, zero on fixed dofs. Thread-safe.
    `single`: factored in float32 (linsolve.py), for the error estimate's solves alone."""

    def __init__(self, mesh: TetMesh, material: NeoHookean, backend: str | None = None, single: bool = False) -> None:
        self.mesh = mesh
        self.material = material
        K0 = Assembler(mesh, material).stiffness_at_rest()
        self._solver = make_solver(K0, backend, single)
        self._solver.factor(K0)
        self._lock = threading.Lock()  # a factorisation's solve is not reentrant (PARDISO)

    def solve_free(self, b: Array) -> Array:
        """K0^-1 b on the free dofs alone (the factorisation's own system). Shape: (f,) or (f, m)."""
        with self._lock:
            return self._solver.solve(b)

    def solve(self, f: Array, chunk: int = 1024) -> Array:
        """u = K0^-1 f for loads on every dof (fixed dofs' entries ignored), in column chunks
        (PARDISO's workspace grows with the right-hand sides). Shape: (3n,) or (3n, m) -> same."""
        f = np.asarray(f, np.float64)
        free = self.mesh.free_dofs
        out = np.zeros(f.shape)
        if f.ndim == 1:
            out[free] = self.solve_free(f[free])
            return out
        for i in range(0, f.shape[1], chunk):
            out[free, i : i + chunk] = self.solve_free(np.ascontiguousarray(f[free, i : i + chunk]))
        return out

    def response(self, nodes: Array) -> Array:
        """Displacement of every node per unit force on each of `nodes`' dofs: column 3 a + i
        answers a unit force on nodes[a], axis i. Shape: (k,) -> (3n, 3k)."""
        nodes = np.asarray(nodes, np.int64)
        k = nodes.size
        rhs = np.zeros((3 * self.mesh.n_nodes, 3 * k))
        rhs[(3 * nodes[:, None] + np.arange(3)).ravel(), np.arange(3 * k)] = 1.0
        return self.solve(rhs)

    def displacements(self, forces: Array, nodes: Array) -> Array:
        """Linear displacements for a batch of loads on `nodes`. Shape: (B, k, 3) -> (B, 3n)."""
        forces = np.asarray(forces, np.float64).reshape(len(forces), -1)
        rhs = np.zeros((3 * self.mesh.n_nodes, len(forces)))
        rhs[(3 * np.asarray(nodes, np.int64)[:, None] + np.arange(3)).ravel()] = forces.T
        return self.solve(rhs).T


#: the range finder's extra directions and power iterations: on the phantom's 592-node region
#: the network's rank-64 linear block is then within 2 % of the SVD's optimum in the 2-norm
#: (docs/performance.md)
OVERSAMPLE, POWER = 16, 2


def leading_directions(
    forward: Callable[[Array], Array], back: Callable[[Array], Array], n_cols: int, rank: int,
    oversample: int, power: int,
) -> tuple[Array, Array]:  # fmt: skip
    """The leading `rank` singular directions of a linear map J (m, n_cols) known by its
    products alone, `forward` X -> J X and `back` Y -> J^T Y: a randomised range finder with
    `oversample` extra directions and `power` power iterations, (2 power + 2)(rank + oversample)
    products in all where the dense J takes n_cols and an SVD. Seeded: the same map gives the
    same directions. Shape: columns (m, r), rows (r, n_cols) with J ~ columns @ rows and the
    rows orthonormal."""
    omega = np.random.default_rng(0).standard_normal((n_cols, min(rank + oversample, n_cols)))
    Q = np.linalg.qr(forward(omega))[0]
    for _ in range(power):
        Q = np.linalg.qr(forward(np.linalg.qr(back(Q))[0]))[0]
    Ub, S, Vt = np.linalg.svd(back(Q).T, full_matrices=False)  # Q^T J = Ub S Vt
    return (Q @ Ub[:, :rank]) * S[:rank], np.ascontiguousarray(Vt[:rank])


def rest_compliance(
    mesh: TetMesh, material: NeoHookean, backend: str | None = None, single: bool = False
) -> RestCompliance:
    """The (kept) rest compliance of this mesh and material."""
    key = (mesh.hash, float(material.E), float(material.nu), backend, single)
    with _cache_lock:
        hit = _cache.get(key)
        if hit is not None:
            _cache.move_to_end(key)
            return hit
    made = RestCompliance(mesh, material, backend, single)  # outside the lock: a factorisation takes time
    with _cache_lock:
        _cache[key] = made
        while len(_cache) > _KEEP:
            _cache.popitem(last=False)
    return made

"""How far to trust a frame, without the ground truth.

A frame's displacement u was produced for forces g by some forward model. The exact (discrete)
physics asks ``f_int(u) = g`` on the free nodes; the residual ``r = f_int(u) - g`` says how far u
is from the equilibrium of its own forces, and one solve with the rest stiffness turns it into a
displacement, ``d = K0^-1 r ~ u - u_eq``, the linearised error of u against that equilibrium. Its mean nodal
norm estimates the forward model's error (a network's; the FEM's is its Newton tolerance).

The registration adds its own error: points it could not explain. The cloud's RMS distance to
the registered surface, beyond the noise the session declared, is a floor on the error where the
camera looks. The estimate is the sum of the two: it errs on the large side rather than the
small one, which is the side a display can act on.

The rest stiffness is factorised once per forward model (shared by its sessions, solves under a
lock); one estimate costs an internal-force evaluation and a back-substitution.
"""

from __future__ import annotations

import threading

import numpy as np

from ..fem.assembly import Assembler
from ..fem.linsolve import make_solver
from ..fem.material import NeoHookean
from ..mesh import TetMesh

Array = np.ndarray

_CACHE_KEY = "_elastreg_residual_estimator"
_CACHE_LOCK = threading.Lock()


class ResidualEstimator:
    """The forward error of a displacement from its Neo-Hookean residual (see the module)."""

    def __init__(self, mesh: TetMesh, material: NeoHookean, backend: str | None = None) -> None:
        self.mesh = mesh
        self.assembler = Assembler(mesh, material)
        K0 = self.assembler.stiffness_at_rest()
        self._solver = make_solver(K0, backend)
        self._solver.factor(K0)
        self._lock = threading.Lock()  # a factorisation's solve is not reentrant (PARDISO)

    def correction(self, u: Array, forces: Array, support: Array) -> Array:
        """d = K0^-1 (f_int(u) - g) ~ u - u_eq(g): the linearised error of u.

        Shape: u (n, 3), forces (k, 3) on support (k,) -> (n, 3), zero on fixed nodes.
        """
        f = self.assembler.internal_force(u)
        np.subtract.at(f, support, forces)
        r = self.assembler.pack(f)
        if not np.isfinite(r).all():
            return np.full_like(u, np.inf)
        with self._lock:
            d = self._solver.solve(r)
        return self.assembler.unpack(d)

    def forward_error(self, u: Array, forces: Array, support: Array) -> float:
        """Mean nodal norm of :meth:`correction` (length units of the mesh)."""
        d = self.correction(u, forces, support)
        return float(np.linalg.norm(d, axis=1).mean())


def estimator_for(model) -> ResidualEstimator:
    """The model's estimator, made on first use and kept on the (immutable, shared) model."""
    est = model.__dict__.get(_CACHE_KEY)
    if est is None:
        with _CACHE_LOCK:
            est = model.__dict__.get(_CACHE_KEY)
            if est is None:
                backend = getattr(getattr(model, "options", None), "backend", None)
                est = ResidualEstimator(model.mesh, model.material, backend)
                model.__dict__[_CACHE_KEY] = est
    return est


def error_estimate(forward_error: float, distance_rms: float, noise: float | None) -> float:
    """The frame's estimate: forward error plus the misfit the declared noise does not explain."""
    unexplained = max(float(distance_rms) - (noise or 0.0), 0.0)
    if not np.isfinite(forward_error) or not np.isfinite(unexplained):
        return float("inf")
    return float(forward_error + unexplained)

"""The reduced output space: a POD basis of training displacements, and the exact linear
(small-strain) response to region forces expressed in it."""

from __future__ import annotations

import numpy as np
import torch

from ..fem.assembly import Assembler
from ..fem.rest import rest_compliance

Array = np.ndarray


def pod_basis(U: Array, rank: int, seed: int = 0) -> tuple[Array, Array]:
    """Leading left singular vectors of the snapshot matrix (randomised SVD).

    Shape: U (N, 3n) snapshots as rows -> basis (3n, r) orthonormal columns, singular values (r,).
    No mean is removed: zero force gives zero displacement, and the basis must keep that.
    Each column's sign is fixed (fixed_signs), so the same data give the same network on any CPU.
    """
    rank = int(min(rank, *U.shape))
    torch.manual_seed(seed)
    A = torch.from_numpy(np.ascontiguousarray(U, dtype=np.float32)).T  # (3n, N)
    Q, S, _ = torch.svd_lowrank(A, q=min(rank + 16, min(A.shape)), niter=3)
    return fixed_signs(Q[:, :rank].numpy().astype(np.float64)), S[:rank].numpy().astype(np.float64)


def fixed_signs(basis: Array) -> Array:
    """The basis with each column's entry of largest magnitude positive (ties: the lowest index).

    A singular vector's sign is arbitrary, and the SVD's follows rounding (MKL's AVX-512 and
    AVX2 kernels gave opposite ones), so a network fitted to the coefficients would differ too.
    Shape: (m, r) -> (m, r), a new array.
    """
    peak = basis[np.argmax(np.abs(basis), axis=0), np.arange(basis.shape[1])]
    return basis * np.where(peak < 0, -1.0, 1.0)


def linear_response(asm: Assembler, region: Array) -> Array:
    """Small-strain displacement of every node per unit force on each region dof.

    Shape: region (R,) -> (3n, 3R), column 3 a + i answers a unit force on node region[a], axis i.
    One (kept) factorisation of the rest stiffness and 3R right-hand sides.
    """
    return rest_compliance(asm.mesh, asm.material).response(region)

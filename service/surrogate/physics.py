"""The physics layout's linear block on a session's support.

A physics-layout network answers u = L g + remainder(features of L g), L = K0^-1 P the rest
compliance on the support's forces. Restricting an operator folds L into it twice: into the
first layer, as the map from forces to the network's features, and into the readout, as basis
columns whose coefficients are the forces' images (exact up to LINEAR_RANK support dofs, the
leading singular directions beyond).
"""

from __future__ import annotations

import numpy as np

from ..fem.rest import OVERSAMPLE, POWER, RestCompliance, leading_directions

Array = np.ndarray

#: the physics layout's linear block joins a session's basis exactly up to this many support
#: dofs; a larger support's block keeps its leading singular directions (the compliance's
#: spectrum decays fast), so the operator's basis is r + this at most. On the liver's 105-node
#: supports 64 registered as the exact block did at half its readout (calibration sites,
#: reports/layout-study/linear_rank.json)
LINEAR_RANK = 64


def physics_input(C: RestCompliance, F: Array, sf: float, support: Array, x_scale: float) -> tuple[Array, Array, Array]:
    """For a physics-layout operator on `support` (k nodes), with C the compliance at the
    trained E0, F (3n, q) the network's feature basis and sf = E0 / E: the map from the
    support's forces to the network's input (q, 3k), and the linear response as basis columns
    (3n, s) with the rows (s, 3k) that turn forces into their coefficients: identity for
    s = 3k, else the leading LINEAR_RANK singular directions. The linear response is at the
    session's E (scaled from E0). A support whose 3k solves outnumber the range finder's (a
    support change to a whole region) takes :func:`leading_response`, not a dense response
    and its SVD."""
    l = LINEAR_RANK + OVERSAMPLE
    if 3 * support.size > F.shape[1] + (2 * POWER + 2) * l:
        dofs = (3 * support[:, None] + np.arange(3)).ravel()
        inmap = C.solve(F)[dofs].T * x_scale  # F^T K0^-1 P: K0 is symmetric, so q solves, not 3k
        L, rows = leading_response(C, dofs, sf)
        return inmap.astype(np.float32), L, rows
    L = C.response(support) * sf  # (3n, 3k), metres per newton
    inmap = (F.T @ L) * (x_scale / sf)
    if L.shape[1] <= LINEAR_RANK:
        rows = np.eye(L.shape[1])
    else:
        W, sv, Vt = np.linalg.svd(L, full_matrices=False)
        L, rows = W[:, :LINEAR_RANK] * sv[:LINEAR_RANK], Vt[:LINEAR_RANK]
    return inmap.astype(np.float32), L, rows


def leading_response(C: RestCompliance, dofs: Array, scale: float) -> tuple[Array, Array]:
    """The leading LINEAR_RANK singular directions of L = scale K0^-1 P (P: unit forces on
    `dofs`) by rest.leading_directions: (2 POWER + 2)(LINEAR_RANK + OVERSAMPLE) solves, where
    the dense route takes one per dof and an SVD (on the phantom's 592-node region 2.8 s of SVD
    and 1.4 s of solves). Shape: (3n, r) columns, (r, 3k) rows."""
    n3 = 3 * C.mesh.n_nodes

    def forward(X: Array) -> Array:  # L X
        rhs = np.zeros((n3, X.shape[1]))
        rhs[dofs] = X
        return C.solve(rhs) * scale

    def back(Y: Array) -> Array:  # L^T Y, K0 symmetric
        return C.solve(Y)[dofs] * scale

    return leading_directions(forward, back, dofs.size, LINEAR_RANK, OVERSAMPLE, POWER)

"""Compiled Neo-Hookean kernels (numba): one fused pass over the tets per quantity.

The NumPy assembly in :mod:`.assembly` is the reference; these compute the same numbers in one
loop per tet that never materialises the (t, 144) element-matrix array, which is what makes the
vectorised version memory-bound (about 22 ms for the liver's tangent against about 3 ms here).
Tests check both paths agree. Plain functions, compiled by :func:`service.jit.kernels` (numba
on first use, machine code cached on disk): ``compiled()`` gives them, or None without numba.
"""

from __future__ import annotations

import math

import numpy as np

from ..jit import kernels


def _gradient(u, tets, grads, t, H):
    """H = grad u = F - I of tet t, summed from zero (its small entries keep their digits)."""
    for i in range(3):
        for J in range(3):
            H[i, J] = 0.0
    for a in range(4):
        n = tets[t, a]
        for i in range(3):
            ui = u[n, i]
            for J in range(3):
                H[i, J] += ui * grads[t, a, J]


def _deformation(u, tets, grads, t, F):
    """F = I + grad u of tet t."""
    _gradient(u, tets, grads, t, F)
    for i in range(3):
        F[i, i] += 1.0


def _inv_transpose(F, G):
    """G = F^-T (non-finite where F is singular); returns det F."""
    c00 = F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1]
    c01 = F[1, 2] * F[2, 0] - F[1, 0] * F[2, 2]
    c02 = F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]
    det = F[0, 0] * c00 + F[0, 1] * c01 + F[0, 2] * c02
    # a singular F (a field 1e29 m large cancels to det 0) gives non-finite values, as NumPy's
    # division does, not numba's ZeroDivisionError: callers read them as an inverted element
    inv = 1.0 / det if det != 0.0 else math.inf
    G[0, 0] = c00 * inv
    G[0, 1] = c01 * inv
    G[0, 2] = c02 * inv
    G[1, 0] = (F[0, 2] * F[2, 1] - F[0, 1] * F[2, 2]) * inv
    G[1, 1] = (F[0, 0] * F[2, 2] - F[0, 2] * F[2, 0]) * inv
    G[1, 2] = (F[0, 1] * F[2, 0] - F[0, 0] * F[2, 1]) * inv
    G[2, 0] = (F[0, 1] * F[1, 2] - F[0, 2] * F[1, 1]) * inv
    G[2, 1] = (F[0, 2] * F[1, 0] - F[0, 0] * F[1, 2]) * inv
    G[2, 2] = (F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]) * inv
    return det


def energy(u, tets, grads, vol, mu, lam):
    """sum_e vol_e W(F_e); +inf if any det F <= 0. J - 1 and tr C - 3 come from H = F - I's
    invariants, not as differences of numbers near 1: near rest those roundings (eps a tet)
    exceeded a small load's whole energy change, and Newton's line search could not see it."""
    H = np.empty((3, 3))
    total = 0.0
    for t in range(tets.shape[0]):
        _gradient(u, tets, grads, t, H)
        tr = H[0, 0] + H[1, 1] + H[2, 2]
        minors = (
            (H[0, 0] * H[1, 1] - H[0, 1] * H[1, 0])
            + (H[0, 0] * H[2, 2] - H[0, 2] * H[2, 0])
            + (H[1, 1] * H[2, 2] - H[1, 2] * H[2, 1])
        )
        det = (
            H[0, 0] * (H[1, 1] * H[2, 2] - H[1, 2] * H[2, 1])
            - H[0, 1] * (H[1, 0] * H[2, 2] - H[1, 2] * H[2, 0])
            + H[0, 2] * (H[1, 0] * H[2, 1] - H[1, 1] * H[2, 0])
        )
        jm1 = tr + minors + det  # det(I + H) - 1
        if jm1 <= -1.0:
            return np.inf
        hh = 0.0
        for i in range(3):
            for J in range(3):
                hh += H[i, J] * H[i, J]
        lnJ = math.log1p(jm1)
        total += vol[t] * (0.5 * mu * (2.0 * tr + hh) - mu * lnJ + 0.5 * lam * lnJ * lnJ)
    return total


def internal_force(u, tets, grads, vol, mu, lam, out):
    """out (n, 3) = dE/du. NaN-free only where det F > 0 (callers check the energy first)."""
    out[:] = 0.0
    F = np.empty((3, 3))
    G = np.empty((3, 3))
    for t in range(tets.shape[0]):
        _deformation(u, tets, grads, t, F)
        det = _inv_transpose(F, G)
        s = lam * math.log(det)
        for a in range(4):
            n = tets[t, a]
            for i in range(3):
                acc = 0.0
                for J in range(3):
                    P = mu * (F[i, J] - G[i, J]) + s * G[i, J]
                    acc += P * grads[t, a, J]
                out[n, i] += vol[t] * acc


def tangent_data(u, tets, grads, vol, mu, lam, slot, data):
    """Tangent values into a CSR data array: data[slot[e]] += K_e for every element entry e.

    slot (t * 144,) maps entry (t, a, i, b, k) to its CSR position, or -1 for fixed dofs.
    K_e = vol [mu (gN_a . gN_b) d_ik + lam v_ai v_bk + (mu - lam ln J) v_ak v_bi], v = F^-T gN.
    """
    data[:] = 0.0
    F = np.empty((3, 3))
    G = np.empty((3, 3))
    v = np.empty((4, 3))
    for t in range(tets.shape[0]):
        _deformation(u, tets, grads, t, F)
        det = _inv_transpose(F, G)
        for a in range(4):
            for i in range(3):
                acc = 0.0
                for J in range(3):
                    acc += G[i, J] * grads[t, a, J]
                v[a, i] = acc
        lv = lam * vol[t]
        cv = (mu - lam * math.log(det)) * vol[t]
        mv = mu * vol[t]
        base = t * 144
        for a in range(4):
            for b in range(4):
                gab = mv * (
                    grads[t, a, 0] * grads[t, b, 0] + grads[t, a, 1] * grads[t, b, 1] + grads[t, a, 2] * grads[t, b, 2]
                )
                for i in range(3):
                    for k in range(3):
                        s = slot[base + (a * 3 + i) * 12 + b * 3 + k]
                        if s >= 0:
                            val = lv * v[a, i] * v[b, k] + cv * v[a, k] * v[b, i]
                            if i == k:
                                val += gab
                            data[s] += val


compiled = kernels(energy, internal_force, tangent_data, helpers=(_gradient, _deformation, _inv_transpose))

"""The compressible Neo-Hookean law of SCENES.md, pointwise over arrays of deformation gradients.

    W(F) = mu/2 (tr C - 3) - mu ln J + lambda/2 (ln J)^2,   C = F^T F,  J = det F

Every function takes F of shape (..., 3, 3) and works on all leading axes at once. Where
J <= 0 the energy is +inf: the line search reads that as "step too long", never as a number.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

from ..material_range import E_RANGE, NU_RANGE

Array = np.ndarray


def det3(F: Array) -> Array:
    """Determinant of (..., 3, 3), written out (faster than np.linalg.det for tiny matrices)."""
    return (
        F[..., 0, 0] * (F[..., 1, 1] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 1])
        - F[..., 0, 1] * (F[..., 1, 0] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 0])
        + F[..., 0, 2] * (F[..., 1, 0] * F[..., 2, 1] - F[..., 1, 1] * F[..., 2, 0])
    )


def inv_transpose(F: Array, J: Array) -> Array:
    """F^{-T} = cof(F) / J, for (..., 3, 3)."""
    c = np.empty_like(F)
    c[..., 0, 0] = F[..., 1, 1] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 1]
    c[..., 0, 1] = F[..., 1, 2] * F[..., 2, 0] - F[..., 1, 0] * F[..., 2, 2]
    c[..., 0, 2] = F[..., 1, 0] * F[..., 2, 1] - F[..., 1, 1] * F[..., 2, 0]
    c[..., 1, 0] = F[..., 0, 2] * F[..., 2, 1] - F[..., 0, 1] * F[..., 2, 2]
    c[..., 1, 1] = F[..., 0, 0] * F[..., 2, 2] - F[..., 0, 2] * F[..., 2, 0]
    c[..., 1, 2] = F[..., 0, 1] * F[..., 2, 0] - F[..., 0, 0] * F[..., 2, 1]
    c[..., 2, 0] = F[..., 0, 1] * F[..., 1, 2] - F[..., 0, 2] * F[..., 1, 1]
    c[..., 2, 1] = F[..., 0, 2] * F[..., 1, 0] - F[..., 0, 0] * F[..., 1, 2]
    c[..., 2, 2] = F[..., 0, 0] * F[..., 1, 1] - F[..., 0, 1] * F[..., 1, 0]
    return c / J[..., None, None]


@dataclasses.dataclass(frozen=True)
class NeoHookean:
    """Material constants and the law. E in pascals and nu dimensionless, within E_RANGE and
    NU_RANGE (service/material_range.py)."""

    E: float
    nu: float

    def __post_init__(self) -> None:
        if not E_RANGE[0] <= self.E <= E_RANGE[1]:  # NaN fails too
            raise ValueError(f"Young's modulus E must be within [{E_RANGE[0]:g}, {E_RANGE[1]:g}] Pa, got {self.E!r}")
        if not NU_RANGE[0] <= self.nu <= NU_RANGE[1]:
            raise ValueError(f"Poisson's ratio nu must be within [{NU_RANGE[0]:g}, {NU_RANGE[1]:g}], got {self.nu!r}")

    law = "neo-hookean"

    @property
    def mu(self) -> float:
        return self.E / (2.0 * (1.0 + self.nu))

    @property
    def lam(self) -> float:
        return self.E * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))

    @classmethod
    def of(cls, spec) -> NeoHookean:
        """The law a scene's [material] table or a manifest's "material" names: anything with
        E and nu, as attributes or keys."""
        get = spec.__getitem__ if isinstance(spec, Mapping) else spec.__getattribute__
        return cls(float(get("E")), float(get("nu")))

    def with_stiffness(self, E: float) -> NeoHookean:
        return dataclasses.replace(self, E=float(E))

    # -- pointwise law ------------------------------------------------------------------------

    def energy(self, F: Array) -> Array:
        """W(F). Shape: (..., 3, 3) -> (...); +inf where det F <= 0. J - 1 and tr C - 3 come
        from H = F - I's invariants, not as differences of numbers near 1 (kernels.energy)."""
        H = F - np.eye(3)
        tr = np.einsum("...ii->...", H)
        minors = (
            (H[..., 0, 0] * H[..., 1, 1] - H[..., 0, 1] * H[..., 1, 0])
            + (H[..., 0, 0] * H[..., 2, 2] - H[..., 0, 2] * H[..., 2, 0])
            + (H[..., 1, 1] * H[..., 2, 2] - H[..., 1, 2] * H[..., 2, 1])
        )
        jm1 = tr + minors + det3(H)  # det(I + H) - 1
        ok = jm1 > -1.0
        lnJ = np.log1p(np.where(ok, jm1, 0.0))
        hh = np.einsum("...ij,...ij->...", H, H)  # tr C - 3 = 2 tr H + |H|^2
        W = 0.5 * self.mu * (2.0 * tr + hh) - self.mu * lnJ + 0.5 * self.lam * lnJ**2
        return np.where(ok, W, np.inf)

    def stress(self, F: Array) -> Array:
        """First Piola-Kirchhoff stress P = dW/dF. Shape: (..., 3, 3)."""
        J = det3(F)
        Finvt = inv_transpose(F, J)
        return self.mu * (F - Finvt) + (self.lam * np.log(J))[..., None, None] * Finvt

    def tangent(self, F: Array) -> Array:
        """dP/dF as A[..., i, J, k, L] = d P_iJ / d F_kL. Shape: (..., 3, 3, 3, 3).

        A = mu I(x)I + (mu - lam ln J) F^-T_iL F^-T_kJ + lam F^-T_iJ F^-T_kL.
        """
        J = det3(F)
        G = inv_transpose(F, J)
        c = self.mu - self.lam * np.log(J)
        eye = np.eye(3)
        A = self.mu * np.einsum("ik,JL->iJkL", eye, eye) * np.ones(F.shape[:-2] + (1,) * 4)
        A = A + c[..., None, None, None, None] * np.einsum("...iL,...kJ->...iJkL", G, G)
        A = A + self.lam * np.einsum("...iJ,...kL->...iJkL", G, G)
        return A

    def cauchy(self, F: Array) -> Array:
        """Cauchy stress sigma = P F^T / J. Shape: (..., 3, 3)."""
        J = det3(F)
        return np.einsum("...iJ,...kJ->...ik", self.stress(F), F) / J[..., None, None]

"""The reduced network's Jacobian dc/dg (c its basis coefficients) and its Gram C C^T.

C = R W1 + S: R = dc/dz the layers above the first at the current PReLU slopes, W1 the first
layer, S the skip path. The Levenberg-Marquardt driver needs C C^T and products with C at every
step; these classes give them without products over the network's K inputs: the first layer's
part factored once per operator (:class:`GramFactors`), the slopes' part corrected by the units
that flipped since the last step (:class:`AnchoredGram`), both behind
:class:`CoefficientJacobian`.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.linalg.blas import sgemm, strmm

from .layers import BlockDiagonal

Array = np.ndarray


def above_first(W_last: Array, tape: list, dtype=np.float32) -> Array:
    """dc/dz (r, h), z the first layer's pre-activation: reverse mode through the layers above
    it at the tape's slopes, r rows. dc/dg is this times the first layer, plus the skip path."""
    R = W_last.astype(dtype, copy=False)
    for W, slope in reversed(tape[1:]):
        R = (R * slope.astype(dtype, copy=False)) @ W.astype(dtype, copy=False)
    return R * tape[0][1].astype(dtype, copy=False)


class GramFactors:
    """The first layer's part of C C^T, once per operator.

    C = R W1 + S (R: the layers above the first, at the current slopes; W1 (h, K) the first
    layer; S (r, K) the skip path). With W1^T = V T (QR, T upper triangular (h, h)):
    C C^T = Y Y^T + E, Y = R T^T + Z^T, Z = V^T S^T (h, r), E = S (I - V V^T) S^T, so an
    iteration costs an (r, h) by (h, h) triangular product and an (r, h) Gram, not products
    over the K inputs (the beam: 939 of them against h = 128; 63 us). :class:`AnchoredGram`
    keeps Y at recent slopes and corrects it by the units that flipped.
    """

    def __init__(self, W1: Array, skip: Array) -> None:
        V, T = np.linalg.qr(W1.T.astype(np.float64))  # (K, q), (q, h), q = min(K, h)
        S = skip.astype(np.float64)
        Z = V.T @ S.T  # (q, r)
        self.T = np.asfortranarray(T, np.float32)  # for BLAS trmm: half a dense product's work
        self.Tt = np.ascontiguousarray(T.T, np.float32)
        self.Zt = np.ascontiguousarray(Z.T, np.float32)
        self.E = S @ S.T - Z.T @ Z  # (r, r), float64

    def Y(self, R: Array) -> Array:
        """R T^T + Z^T (r, q)."""
        if self.T.shape[0] == self.T.shape[1]:
            Y = strmm(1.0, self.T, R, side=1, lower=0, trans_a=1)  # R T^T
        else:  # fewer inputs than units (K < h): T is K x h, no triangle to exploit
            Y = R @ self.Tt
        Y += self.Zt
        return Y


@dataclasses.dataclass(frozen=True)
class _Anchor:
    """What :class:`AnchoredGram` corrects from: the slopes it was made at (s2 None for one
    hidden layer), P, Y and Y Y^T there, and how many corrections it has taken since a full
    refresh."""

    s1: Array
    s2: Array | None
    P: Array
    Y: Array
    YY: Array
    corrections: int


class AnchoredGram:
    """R = dc/dz (z the first layer's pre-activation) and C C^T at the slopes last seen,
    corrected by the PReLU units whose slope changed since, for networks of one or two hidden
    layers (deeper ones: in full at every call).

    With P the layers above the first hidden layer's activation (W_last for one hidden layer,
    (W_last D2) W2 for two, D the slopes), R = P D1 and Y = R T^T + Z^T (GramFactors), so
    C C^T = Y Y^T + E. A step that flips k units changes P by W_last[:, F2] dD2 W2[F2] and R
    by that times D1 plus P[:, F1] dD1: Y changes by a rank-k product L N and Y Y^T by
    Y N^T L^T + L N Y^T + L (N N^T) L^T, about k h (h + 3 r) products against the full
    r h (h + h2 + r). Warm-started frames on the paper's liver flip one or two of its 512 top
    units per step (median; 49 at most): the Jacobian and its Gram there cost 3.5 ms a step in
    full. Refreshed in full when the correction would cost a quarter of that or more, and
    after _REFRESH corrections (float32 drift).
    """

    _REFRESH = 16
    _SHARE = 0.6

    def __init__(self, W_last: Array, tape: list, factors: GramFactors) -> None:
        self.W_last, self._f = W_last, factors
        self._deep = len(tape) > 2
        self.W_top = tape[1][0] if len(tape) == 2 else None  # the second hidden layer's weights
        r, h, q = W_last.shape[0], tape[0][0].shape[0], factors.Tt.shape[1]
        h2 = 0 if self.W_top is None else self.W_top.shape[0]
        blocks = self.W_top.blocks.shape[0] if isinstance(self.W_top, BlockDiagonal) else 1
        self._full_cost = r * h2 * (h // blocks) + r * h * q + r * q * r  # P, Y and Y Y^T
        self._unit_cost = h * q + r * h + 2 * r * q + r * r  # a row of N; P, Y and Y Y^T updated
        self._anchor: _Anchor | None = None

    def at(self, tape: list) -> tuple[Array, Array]:
        """(R (r, h) Fortran-ordered float32, C C^T (r, r) float64 read-only) at the tape's slopes."""
        if self._deep:
            R = np.asfortranarray(above_first(self.W_last, tape))
            Y = self._f.Y(R)
            return R, self._gram((Y @ Y.T).astype(np.float64))
        s1 = tape[0][1]
        s2 = tape[1][1] if self.W_top is not None else None
        a = self._anchor
        if a is not None and a.corrections < self._REFRESH:
            F1 = np.flatnonzero(s1 != a.s1)
            F2 = np.flatnonzero(s2 != a.s2) if s2 is not None else F1[:0]
            k = F1.size + F2.size
            if k * self._unit_cost < self._SHARE * self._full_cost:
                P, Y, YY = self._correct(a, s1, F1, s2, F2) if k else (a.P, a.Y, a.YY)
                self._anchor = _Anchor(s1, s2, P, Y, YY, a.corrections + (k > 0))
                return self._result(P, s1, YY)
        P = np.asfortranarray(self.W_last if self.W_top is None else (self.W_last * s2) @ self.W_top)
        Y = self._f.Y(P * s1)  # P Fortran-ordered, so is the product: BLAS trmm takes it as is
        YY = (Y @ Y.T).astype(np.float64)
        self._anchor = _Anchor(s1, s2, P, Y, YY, 0)
        return self._result(P, s1, YY)

    def _correct(self, a: _Anchor, s1: Array, F1: Array, s2: Array | None, F2: Array):
        """P, Y and Y Y^T after the units F1 (first layer) and F2 (second) changed slopes from
        the anchor's to s1 and s2."""
        Tt = self._f.Tt  # T^T (h, q)
        P, Y, YY = a.P, a.Y, a.YY
        parts_L, parts_N = [], []
        if F2.size:
            L2 = self.W_last[:, F2] * (s2 - a.s2)[F2]  # (r, f2)
            M2 = self.W_top[F2]  # (f2, h)
            parts_L.append(L2)
            parts_N.append((M2 * s1) @ Tt)
        if F1.size:
            parts_L.append(P[:, F1] * (s1 - a.s1)[F1])
            parts_N.append(Tt[F1])
        L = np.hstack(parts_L) if len(parts_L) > 1 else parts_L[0]  # (r, k)
        N = np.vstack(parts_N) if len(parts_N) > 1 else parts_N[0]  # (k, q)
        if F2.size:
            # BLAS in place, in P's (Fortran) order: NumPy's product of a few columns by a few
            # rows and its sum across orders cost 1 ms at the liver's 192 x 1536
            P = sgemm(1.0, L2, M2, beta=1.0, c=P.copy(order="F"), overwrite_c=True)
        A = (Y @ N.T).astype(np.float64)  # Y N^T with the Y before the change
        B = L.astype(np.float64)
        BA = B @ A.T
        YY = YY + BA + BA.T + B @ (N.astype(np.float64) @ N.T.astype(np.float64)) @ B.T
        return P, Y + L @ N, YY

    def _result(self, P, s1, YY) -> tuple[Array, Array]:
        return P * s1, self._gram(YY)

    def _gram(self, YY: Array) -> Array:
        G = YY + self._f.E
        G.flags.writeable = False
        return G


class CoefficientJacobian:
    """dc/dg = C (r, K) of the reduced network at one input, in product form: C = R W1 + S with
    R = dc/dz (r, h) the layers above the first (see :class:`AnchoredGram`). ``U`` (3p, r)
    is the readout of the operator's nodes (du/dc, constant), so du/dg = U C."""

    def __init__(
        self, readout: Array, R: Array, gram: Array, stacked: Array, pulled: tuple[Array, Array] | None = None
    ) -> None:
        self.R = R  # (r, h)
        self.U = readout
        self._P = stacked  # [W1; S] (h + r, K): C = [R, I] P
        self._gram = gram
        self._pulled = pulled  # (U^T u_bar, P g) of the operator's last evaluation, at this g

    def with_gradient(self, coef_bar: Array, projected: Array) -> CoefficientJacobian:
        """This Jacobian, also knowing the last evaluation's pullback at its point: the
        coefficients' adjoint U^T u_bar (r,) and the stacked input product P g (h + r,)."""
        return CoefficientJacobian(self.U, self.R, self._gram, self._P, (coef_bar, projected))

    def gradient_image(self, alpha: float) -> Array | None:
        """C grad for the gradient the last evaluation gave at this point, grad = C^T U^T u_bar
        + alpha g, as C C^T (U^T u_bar) + alpha (R W1 g + S g): small products with the Gram
        and P g, not a product over the K inputs (the beam: 939). None when unknown. (r,)"""
        if self._pulled is None:
            return None
        coef_bar, px = self._pulled
        h = self.R.shape[1]
        Cg = (self.R @ px[:h]).astype(np.float64)
        if px.size > h:
            Cg += px[h:]
        return self._gram @ coef_bar.astype(np.float64) + alpha * Cg

    def gram(self) -> Array:
        """C C^T (r, r), float64, read-only."""
        return self._gram

    def gram_product(self, A: Array) -> Array:
        """C C^T A (r, r) for a symmetric A, in Fortran order as LAPACK takes it: (A C C^T)^T,
        both symmetric."""
        return (A @ self._gram).T

    def matvec(self, v: Array) -> Array:
        """C v. Shape: (K,) -> (r,), float64."""
        h = self.R.shape[1]
        p = self._P @ np.asarray(v, np.float32)
        return (self.R @ p[:h] + p[h:]).astype(np.float64)

    def rmatvec(self, w: Array) -> Array:
        """C^T w. Shape: (r,) -> (K,), float64."""
        h = self.R.shape[1]
        y = np.asarray(w, np.float32)
        return (self._P[:h].T @ (self.R.T @ y) + self._P[h:].T @ y).astype(np.float64)

"""The network forward model: a trained surrogate behind the registration interface.

Training happens in torch; the real-time loop runs the same network as a few float32 NumPy
matrix-vector products with a hand-written backward pass (the adjoint of the paper, eq. 9):
for one sample, torch's per-operation and autograd overheads cost ~9x more than the arithmetic
(measured: 5.9 ms against 0.67 ms for forward + backward). Tests check the NumPy pullback
against torch autograd on the trained module.

Restricting an operator to a session slices the network once: the first layer keeps only the
columns of the support's force dofs, and the readout only the rows of the nodes the objective
reads. Stiffness enters through the exact scaling u(g; E) = u(g E0 / E; E0) of the Neo-Hookean
energy at fixed nu, folded into the first layer.
"""

from __future__ import annotations

import dataclasses
import functools
import threading
from collections.abc import Callable

import numpy as np
import torch
from scipy.linalg.blas import sgemm, strmm

from ..fem.material import NeoHookean
from ..fem.rest import OVERSAMPLE, POWER, RestCompliance, leading_directions, rest_compliance
from ..forward import check_support
from ..mesh import TetMesh
from .network import Ensemble, PaperSurrogate, ReducedSurrogate

Array = np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class NetworkModel:
    """A trained surrogate for one mesh, material and load region. Immutable; shared."""

    mesh: TetMesh
    material: NeoHookean  # the session's material (E may differ from the trained E0)
    region: Array  # (R,) node ids whose forces the network reads
    net: torch.nn.Module
    E0: float  # Young's modulus the network was trained at
    max_force: float | None = None  # N: the error estimate's force prior (FEMModel.max_force)
    tool_patch: int | None = None  # nodes under one tool at most (FEMModel.tool_patch)

    method = "network"

    def __post_init__(self) -> None:
        self.net.eval()
        pos = np.full(self.mesh.n_nodes, -1, np.int64)
        pos[self.region] = np.arange(len(self.region))
        object.__setattr__(self, "_region_pos", pos)

    @property
    def physics(self) -> bool:
        """The physics layout: linear response outside the network, its features inside."""
        return bool(getattr(self.net, "physics", False))

    def compliance(self) -> RestCompliance:
        """K0^-1 at the trained E0 (shared by every model and session on this mesh)."""
        return rest_compliance(self.mesh, self.material.with_stiffness(self.E0))

    def with_stiffness(self, E: float) -> NetworkModel:
        # the same problem in forces scaled by E / E_now: the largest tool force too (the estimate's prior)
        scaled = None if self.max_force is None else self.max_force * (E / self.material.E)
        return dataclasses.replace(self, material=self.material.with_stiffness(E), max_force=scaled)

    @property
    def stiffness_factor(self) -> float:
        """E0 / E: the factor forces are scaled by before the network sees them."""
        return self.E0 / self.material.E

    def region_columns(self, support: Array) -> Array:
        """Input columns (3 per node) of the support's nodes. Shape: (k,) -> (3k,)."""
        pos = self._region_pos[support]
        if (pos < 0).any():
            bad = support[pos < 0]
            raise ValueError(
                f"support nodes outside the network's load region: {bad[:10].tolist()}"
                f"{' ...' if bad.size > 10 else ''} (the region has {len(self.region)} nodes; "
                "use method 'fem' or retrain with a larger region)"
            )
        return (3 * pos[:, None] + np.arange(3)).ravel()

    def restrict(self, support: Array, nodes: Array | None = None) -> NetworkOperator:
        return NetworkOperator(self, support, nodes)

    def predict(self, forces: Array, support: Array) -> Array:
        """Displacements for a batch of loads. Shape: (B, k, 3) on support (k,) -> (B, n, 3)."""
        support = check_support(self.mesh, support)
        cols = self.region_columns(support)
        forces = np.asarray(forces, np.float32).reshape(len(forces), -1)
        if self.physics:  # u = L g + remainder(features of L g)
            lin = self.compliance().displacements(forces * self.stiffness_factor, support)
            z = (lin @ self.net.feature_basis.double().numpy()).astype(np.float32)
            with torch.no_grad():
                rem = self.net(torch.from_numpy(z)).numpy()
            return (lin + rem).reshape(len(forces), -1, 3)
        x = np.zeros((len(forces), 3 * len(self.region)), np.float32)
        x[:, cols] = forces * self.stiffness_factor
        with torch.no_grad():
            u = self.net(torch.from_numpy(x)).numpy()
        return u.reshape(len(forces), -1, 3).astype(np.float64)


#: the physics layout's linear block joins a session's basis exactly up to this many support
#: dofs; a larger support's block keeps its leading singular directions (the compliance's
#: spectrum decays fast), so the operator's basis is r + this at most. On the liver's 105-node
#: supports 64 registered as the exact block did at half its readout (calibration sites,
#: reports/layout-study/linear_rank.json)
LINEAR_RANK = 64


def _physics_input(model: NetworkModel, support: Array, x_scale: float) -> tuple[Array, Array, Array]:
    """For a physics-layout operator on `support` (k nodes): the map from the support's forces
    to the network's input (q, 3k), and the linear response as basis columns (3n, s) with the
    rows (s, 3k) that turn forces into their coefficients: identity for s = 3k, else the leading
    LINEAR_RANK singular directions. The linear response is at the session's E (scaled from E0).
    A support whose 3k solves outnumber the range finder's (a support change to a whole
    region) takes :func:`_leading_response`, not a dense response and its SVD."""
    C, sf = model.compliance(), model.stiffness_factor
    F = model.net.feature_basis.double().numpy()
    l = LINEAR_RANK + OVERSAMPLE
    if 3 * support.size > F.shape[1] + (2 * POWER + 2) * l:
        dofs = (3 * support[:, None] + np.arange(3)).ravel()
        inmap = C.solve(F)[dofs].T * x_scale  # F^T K0^-1 P: K0 is symmetric, so q solves, not 3k
        L, rows = _leading_response(C, dofs, sf)
        return inmap.astype(np.float32), L, rows
    L = C.response(support) * sf  # (3n, 3k), metres per newton
    inmap = (F.T @ L) * (x_scale / sf)
    if L.shape[1] <= LINEAR_RANK:
        rows = np.eye(L.shape[1])
    else:
        W, sv, Vt = np.linalg.svd(L, full_matrices=False)
        L, rows = W[:, :LINEAR_RANK] * sv[:LINEAR_RANK], Vt[:LINEAR_RANK]
    return inmap.astype(np.float32), L, rows


def _leading_response(C, dofs: Array, scale: float) -> tuple[Array, Array]:
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


def _mlp_layers(mlp: torch.nn.Sequential) -> list[tuple[Array, Array, Array | None]]:
    """(W, b, PReLU slopes or None) per layer of one MLP, as float32 arrays."""
    mods = list(mlp)
    out = []
    for i, m in enumerate(mods):
        if isinstance(m, torch.nn.Linear):
            nxt = mods[i + 1] if i + 1 < len(mods) else None
            a = None
            if isinstance(nxt, torch.nn.PReLU):
                a = nxt.weight.detach().numpy().astype(np.float32)
                a = np.broadcast_to(a, (m.out_features,)).copy()
            out.append((m.weight.detach().numpy().astype(np.float32), m.bias.detach().numpy().astype(np.float32), a))
    return out


def _layers(net: torch.nn.Module) -> list:
    """(W, b, PReLU slopes or None) per layer of the network's MLP. An ensemble's members
    become one MLP whose hidden units are all the members' side by side: the first layer
    stacked, the layers between block-diagonal (kept as blocks), the last side by side and
    divided by their number (their mean)."""
    if not isinstance(net.net, Ensemble):
        return _mlp_layers(net.net)
    each = [_mlp_layers(m) for m in net.net.members]
    k, depth = len(each), len(each[0])
    out = []
    for i, parts in enumerate(zip(*each, strict=True)):
        Ws, bs, slopes = zip(*parts, strict=True)
        if i == depth - 1:  # the last: the members' mean
            W, b = np.hstack(Ws) / np.float32(k), np.sum(bs, axis=0) / np.float32(k)
        else:
            W = np.vstack(Ws) if i == 0 else BlockDiagonal(np.stack(Ws))
            b = np.concatenate(bs)
        a = None if slopes[0] is None else np.concatenate(slopes)
        out.append((W, b, a))
    return out


class BlockDiagonal:
    """A block-diagonal matrix kept as its blocks (q, m, n): an ensemble's layers between the
    first and the last. Products cost the blocks' q m n, not the dense (q m)(q n) (3 members
    of 512: 0.12 ms against 0.37 ms a product). NumPy defers ``A @ self`` to it."""

    __array_ufunc__ = None  # ndarray @ BlockDiagonal -> BlockDiagonal.__rmatmul__

    def __init__(self, blocks: Array, transposed: BlockDiagonal | None = None) -> None:
        # a transpose reads its original's memory (a view: BLAS takes each block transposed)
        self.blocks = blocks if transposed is not None else np.ascontiguousarray(blocks)
        q, m, n = blocks.shape
        self.shape = (q * m, q * n)
        self.dtype = blocks.dtype
        self._T = transposed

    @property
    def T(self) -> BlockDiagonal:
        """Made once, a view of the same blocks: the pullback's products then read the
        weights the forward pass just read, not a second copy."""
        if self._T is None:
            self._T = BlockDiagonal(self.blocks.transpose(0, 2, 1), transposed=self)
        return self._T

    def astype(self, dtype, copy: bool = True) -> BlockDiagonal:
        if not copy and self.dtype == dtype:
            return self
        return BlockDiagonal(self.blocks.astype(dtype))

    def __matmul__(self, x: Array) -> Array:
        """self @ x for x (q n,) or (q n, c)."""
        q, _, n = self.blocks.shape
        y = np.matmul(self.blocks, x.reshape(q, n, -1))  # (q, m, c)
        return y.reshape(-1) if x.ndim == 1 else y.reshape(-1, x.shape[1])

    def __rmatmul__(self, A: Array) -> Array:
        """A @ self for A (c, q m)."""
        q, m, n = self.blocks.shape
        y = np.matmul(A.reshape(-1, q, m).transpose(1, 0, 2), self.blocks)  # (q, c, n)
        return np.ascontiguousarray(y.transpose(1, 0, 2)).reshape(A.shape[0], q * n)

    def __getitem__(self, rows: Array) -> Array:
        """Dense rows (len(rows), q n): zeros outside each row's block."""
        q, m, n = self.blocks.shape
        rows = np.asarray(rows)
        out = np.zeros((rows.size, q * n), self.dtype)
        blk, r = np.divmod(rows, m)
        cols = blk[:, None] * n + np.arange(n)
        out[np.arange(rows.size)[:, None], cols] = self.blocks[blk, r]
        return out


class NetworkOperator:
    """g on the support -> u on the nodes, and its pullback, as sliced float32 NumPy arrays.

    Shape: g (k, 3) -> u (p, 3); the pullback maps (p, 3) -> (k, 3).
    """

    def __init__(self, model: NetworkModel, support: Array, nodes: Array | None = None) -> None:
        mesh = model.mesh
        self.model = model
        self.support = check_support(mesh, support)
        self.nodes = np.arange(mesh.n_nodes) if nodes is None else np.asarray(nodes, np.int64)
        cols = model.region_columns(self.support)
        net = model.net
        layers = _layers(net)
        if isinstance(net, ReducedSurrogate):
            x_scale = model.stiffness_factor / float(net.force_scale)
            cs = net.coef_scale.numpy().astype(np.float32)
            W_last, b_last, _ = layers[-1]
            layers[-1] = (W_last * cs[:, None], b_last * cs, None)
            basis = net.basis.numpy().astype(np.float32)
            if model.physics:
                inmap, lin_cols, lin_rows = _physics_input(model, self.support, x_scale)
                layers[0] = (layers[0][0] @ inmap, *layers[0][1:])
                skip = (net.skip.weight.detach().numpy() @ inmap) * cs[:, None]
                # the linear response joins the basis: its coefficients are its inputs' images
                W_last, b_last, _ = layers[-1]
                n_lin = lin_rows.shape[0]
                layers[-1] = (np.vstack((W_last, np.zeros((n_lin, W_last.shape[1]), np.float32))),
                              np.concatenate((b_last, np.zeros(n_lin, np.float32))), None)  # fmt: skip
                self._skip = np.vstack((skip, lin_rows)).astype(np.float32)
                basis = np.hstack((basis, lin_cols.astype(np.float32)))
            else:
                self._skip = (net.skip.weight.detach().numpy()[:, cols] * (x_scale * cs[:, None])).astype(np.float32)
                layers[0] = (layers[0][0][:, cols] * x_scale, *layers[0][1:])
            basis = basis.reshape(mesh.n_nodes, 3, -1)
            self._readout = np.ascontiguousarray(basis[self.nodes].reshape(3 * self.nodes.size, -1))
            self._basis_all = basis.reshape(3 * mesh.n_nodes, -1)
        elif isinstance(net, PaperSurrogate):
            x_scale = model.stiffness_factor / float(net.force_scale)
            us = float(net.u_scale)
            W_last, b_last, _ = layers[-1]
            self._last_all = (W_last * us, b_last * us)
            rows = (3 * self.nodes[:, None] + np.arange(3)).ravel()
            layers[-1] = (np.ascontiguousarray(W_last[rows] * us), b_last[rows] * us, None)
            self._skip = None
            self._readout = None
            layers[0] = (layers[0][0][:, cols] * x_scale, *layers[0][1:])
        else:
            raise TypeError(f"unsupported network {type(net).__name__}")
        W0, b0, a0 = layers[0]
        W0 = np.asarray(W0, np.float32)
        # the input's two readers, the first layer and the skip path, stacked: one product
        # with g serves both (the forward pass and C v); the transposed products stay two
        # (a stacked one sums in another order: other roundings, other iterations in the
        # beam's few long registrations)
        self._input = np.ascontiguousarray(W0 if self._skip is None else np.vstack((W0, self._skip)))
        self._n_first = W0.shape[0]
        if self._skip is not None:
            self._skip = self._input[self._n_first :]
        layers[0] = (self._input[: self._n_first], b0, a0)
        self._layers = layers
        self._jac: tuple[Array, Array] | None = None
        self._factors: _GramFactors | None = None  # for jacobian(), made at its first call
        self._rest_jacobian: CoefficientJacobian | None = None  # jacobian(0), kept
        self._anchored: _AnchoredGram | None = None  # jacobian()'s R and C C^T, kept and corrected
        self._tape_at: tuple[Array, list, Array, Array] | None = None  # the last evaluation's
        # input, tape, last hidden layer and P x
        self._last_x: Array | None = None  # the input of the last evaluation (the object)
        self._pulled: tuple[Array, Array, Array] | None = None  # its input, U^T u_bar, P x
        self._row_cache: list[tuple[Array, Array]] = []  # (rows, the readout's rows), last used first
        self._row_lock = threading.Lock()  # at_rest's pullback reads rows beside a frame's own
        self._at_rest: tuple[tuple[Array, Callable[..., Array]], Array] | None = None  # (u, pullback), x

    def reset(self) -> None:  # stateless: nothing to forget
        pass

    def _hidden(self, x: Array) -> tuple[Array, list[tuple[Array, Array | None]], Array]:
        """Forward through all but the last layer; keeps what the backward pass needs. Also
        returns P x, the stacked input product (the first layer's W1 x, then the skip path's
        S x where there is one)."""
        tape = []
        px = self._input @ x
        h = px[: self._n_first]
        for i, (W, b, a) in enumerate(self._layers[:-1]):
            z = (W @ h if i else h) + b
            slope = np.where(z > 0, np.float32(1.0), a)
            tape.append((W, slope))
            h = z * slope
        return h, tape, px

    def _hidden_at(self, x: Array) -> tuple[Array, list[tuple[Array, Array | None]], Array]:
        """:meth:`_hidden` at x, the last evaluation's own when x is its input."""
        at = self._tape_at  # read once: a spare core's displacement() runs beside evaluations
        if at is not None and np.array_equal(at[0], x):
            _, tape, h, px = at
            return h, tape, px
        return self._hidden(x)

    def _skip_of(self, px: Array) -> Array | None:
        """The skip path's S x within P x (None without a skip path)."""
        return px[self._n_first :] if self._skip is not None else None

    def __call__(self, g: Array) -> tuple[Array, Callable[[Array], Array]]:
        x = np.asarray(g, np.float32).reshape(-1)
        if not x.any():
            # the rest state, which the engine evaluates every frame: the same answer each time
            (u, pullback), self._last_x = self._rest_state()
            self._pulled = None  # a new evaluation: its pullback has not run
            return u, pullback
        return self._evaluate(x)

    def at_rest(self) -> tuple[Array, Callable[[Array], Array]]:
        """(u, pullback) at g = 0, as a call at zero gives them, but recording nothing on the
        operator: safe on another thread beside this operator's own evaluations (the engine
        evaluates the rest state there while a warm frame evaluates its start)."""
        (u, pullback), _ = self._rest_state()
        return u, functools.partial(pullback, quiet=True)

    def _rest_state(self) -> tuple[tuple[Array, Callable[..., Array]], Array]:
        """The rest evaluation and its input, made once, and made recording nothing, so that
        either caller (a call at zero, at_rest on another thread) may be the first."""
        rest = self._at_rest
        if rest is None:
            x = np.zeros(self._input.shape[1], np.float32)
            rest = self._at_rest = (self._evaluate(x, record=False), x)
        return rest

    def _evaluate(self, x: Array, record: bool = True) -> tuple[Array, Callable[[Array], Array]]:
        h, tape, px = self._hidden(x)
        skip = self._skip_of(px)
        if record:
            self._tape_at = (x, tape, h, px)
            self._last_x, self._pulled = x, None  # a new evaluation: its pullback has not run
        W_last, b_last, _ = self._layers[-1]
        y = W_last @ h + b_last
        if skip is not None:
            y += skip
        u = self._readout @ y if self._readout is not None else y
        k = x.size // 3

        def pullback(u_bar: Array, rows: Array | None = None, quiet: bool = False) -> Array:
            if self._readout is None:
                yb = np.asarray(u_bar, np.float32).reshape(-1)
            elif rows is not None and rows.size < 0.5 * self.nodes.size:
                # the distance's gradient lives on its candidate triangles' nodes (a fifth of
                # the liver's matching surface): read out through their rows alone, gathered
                # once per candidate index, not the whole (memory-bound) readout
                yb = self._readout_rows(rows).T @ np.asarray(u_bar, np.float32)[rows].reshape(-1)
            else:
                yb = self._readout.T @ np.asarray(u_bar, np.float32).reshape(-1)
            if not quiet and x is self._last_x:  # the latest evaluation's: C grad = C C^T yb + alpha C g
                self._pulled = (x, yb, px)
            hb = W_last.T @ yb
            xb = self._skip.T @ yb if self._skip is not None else 0.0
            for W, slope in reversed(tape):
                hb = W.T @ (hb * slope)
            return (hb + xb).astype(np.float64).reshape(k, 3)

        u = u.astype(np.float64).reshape(-1, 3)
        u.flags.writeable = False  # shared by every call at rest
        return u, pullback

    def _readout_rows(self, rows: Array) -> Array:
        """The readout's rows of these nodes only (3q, r), for the few node sets in use
        (a frame alternates between its indices), keyed by the array object."""
        with self._row_lock:
            for i, (key, R) in enumerate(self._row_cache):
                if key is rows:
                    if i:
                        self._row_cache.insert(0, self._row_cache.pop(i))
                    return R
            r = self._readout.shape[1]
            R = self._readout.reshape(-1, 3, r).take(rows, axis=0).reshape(-1, r)
            self._row_cache = [(rows, R), *self._row_cache[:3]]
            return R

    @property
    def readout(self) -> Array | None:
        """du/dc (3p, r) of the operator's nodes, the same at every g (its Jacobian's U); None
        for the paper's layout (no basis)."""
        return self._readout

    def low_rank_jacobian(self) -> tuple[Array, Array] | None:
        """du/dg at g = 0 as U Q^T, Q orthonormal: the reduced network answers in r basis
        coefficients, so its Jacobian has rank r << 3k (the Gauss-Newton preconditioner's
        input). Reverse mode, r rows, in float64; kept in float32 like the network. Cached.
        Shape: U (3p, r) node-major over the operator's nodes, Q (3k, r); None for the paper's
        layout (no basis)."""
        if self._readout is None:
            return None
        if self._jac is None:
            W1 = self._layers[0][0]
            _, tape, _ = self._hidden(np.zeros(W1.shape[1], np.float32))
            C = (
                _above_first(self._layers[-1][0], tape, np.float64) @ W1.astype(np.float64) + self._skip
            )  # dc/dg (r, 3k)
            Q, Rt = np.linalg.qr(C.T)  # C = Rt^T Q^T
            U = self._readout.astype(np.float64) @ Rt.T
            self._jac = (U.astype(np.float32), np.ascontiguousarray(Q, np.float32))
        return self._jac

    def jacobian(self, g: Array) -> CoefficientJacobian | None:
        """dc/dg at g, c the basis coefficients (u = readout c): the Levenberg-Marquardt
        driver's model. None for the paper's layout (no basis). Reuses the last evaluation's
        slopes when g is where it was."""
        if self._readout is None:
            return None
        x = np.asarray(g, np.float32).reshape(-1)
        at_rest = not x.any()
        if at_rest and self._rest_jacobian is not None:  # every cold frame starts here
            jac = self._rest_jacobian
        else:
            _, tape, _ = self._hidden_at(x)
            if self._factors is None:
                self._factors = _GramFactors(self._layers[0][0], self._skip)
            if self._anchored is None:
                self._anchored = _AnchoredGram(self._layers[-1][0], tape, self._factors)
            R, G = self._anchored.at(tape)
            jac = CoefficientJacobian(self._readout, R, G, self._input)
            if at_rest:
                self._rest_jacobian = jac
        pulled = self._pulled  # only ever the last evaluation's, after its pullback
        if pulled is not None and np.array_equal(pulled[0], x):
            # g is the last evaluation's point and its pullback ran: the gradient's image is
            # known without a product over the K inputs (a fresh object: the rest one is kept)
            jac = jac.with_gradient(pulled[1], pulled[2])
        return jac

    def estimate_jacobian(self, g: Array) -> CoefficientJacobian | None:
        """The error estimate's Jacobian (FEMOperator.estimate_jacobian): the rest one, kept.
        On calibration sites it ranked and bounded frames as the one at g did, 1.2 ms a
        frame cheaper (docs/performance.md)."""
        return self.jacobian(np.zeros_like(np.asarray(g)))

    def displacement(self, g: Array) -> Array:
        """Every node's displacement (the readout over the whole mesh). Shape: (n, 3)."""
        x = np.asarray(g, np.float32).reshape(-1)
        h, _, px = self._hidden_at(x)  # a frame's answer is usually its last evaluation
        skip = self._skip_of(px)
        if self._readout is not None:
            W_last, b_last, _ = self._layers[-1]
            y = W_last @ h + b_last + skip
            u = self._basis_all @ y
        else:
            W_all, b_all = self._last_all
            u = W_all @ h + b_all
        return u.astype(np.float64).reshape(-1, 3)


def _above_first(W_last: Array, tape: list, dtype=np.float32) -> Array:
    """dc/dz (r, h), z the first layer's pre-activation: reverse mode through the layers above
    it at the tape's slopes, r rows. dc/dg is this times the first layer, plus the skip path."""
    R = W_last.astype(dtype, copy=False)
    for W, slope in reversed(tape[1:]):
        R = (R * slope.astype(dtype, copy=False)) @ W.astype(dtype, copy=False)
    return R * tape[0][1].astype(dtype, copy=False)


class _GramFactors:
    """The first layer's part of C C^T, once per operator.

    C = R W1 + S (R: the layers above the first, at the current slopes; W1 (h, K) the first
    layer; S (r, K) the skip path). With W1^T = V T (QR, T upper triangular (h, h)):
    C C^T = Y Y^T + E, Y = R T^T + Z^T, Z = V^T S^T (h, r), E = S (I - V V^T) S^T, so an
    iteration costs an (r, h) by (h, h) triangular product and an (r, h) Gram, not products
    over the K inputs (the beam: 939 of them against h = 128; 63 us). :class:`_AnchoredGram`
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
    """What :class:`_AnchoredGram` corrects from: the slopes it was made at (s2 None for one
    hidden layer), P, Y and Y Y^T there, and how many corrections it has taken since a full
    refresh."""

    s1: Array
    s2: Array | None
    P: Array
    Y: Array
    YY: Array
    corrections: int


class _AnchoredGram:
    """R = dc/dz (z the first layer's pre-activation) and C C^T at the slopes last seen,
    corrected by the PReLU units whose slope changed since, for networks of one or two hidden
    layers (deeper ones: in full at every call).

    With P the layers above the first hidden layer's activation (W_last for one hidden layer,
    (W_last D2) W2 for two, D the slopes), R = P D1 and Y = R T^T + Z^T (_GramFactors), so
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

    def __init__(self, W_last: Array, tape: list, factors: _GramFactors) -> None:
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
            R = np.asfortranarray(_above_first(self.W_last, tape))
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
    R = dc/dz (r, h) the layers above the first (see :class:`_AnchoredGram`). ``U`` (3p, r)
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

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

The network's layers come as NumPy arrays from layers.py, the physics layout's linear block
from physics.py, and the reduced network's Jacobian algebra (CoefficientJacobian) from
jacobian.py.
"""

from __future__ import annotations

import dataclasses
import functools
import threading
from collections.abc import Callable

import numpy as np
import torch

from ..fem.material import NeoHookean
from ..fem.rest import RestCompliance, rest_compliance
from ..forward import check_support
from ..mesh import TetMesh
from .jacobian import AnchoredGram, CoefficientJacobian, GramFactors, above_first
from .layers import network_layers
from .network import PaperSurrogate, ReducedSurrogate
from .physics import physics_input

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
        layers = network_layers(net)
        if isinstance(net, ReducedSurrogate):
            x_scale = model.stiffness_factor / float(net.force_scale)
            cs = net.coef_scale.numpy().astype(np.float32)
            W_last, b_last, _ = layers[-1]
            layers[-1] = (W_last * cs[:, None], b_last * cs, None)
            basis = net.basis.numpy().astype(np.float32)
            if model.physics:
                F = net.feature_basis.double().numpy()
                inmap, lin_cols, lin_rows = physics_input(
                    model.compliance(), F, model.stiffness_factor, self.support, x_scale
                )
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
        self._factors: GramFactors | None = None  # for jacobian(), made at its first call
        self._rest_jacobian: CoefficientJacobian | None = None  # jacobian(0), kept
        self._anchored: AnchoredGram | None = None  # jacobian()'s R and C C^T, kept and corrected
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

    def readout_at(self, nodes: Array) -> Array | None:
        """du/dc at other nodes (3q, r), in its Jacobians' coefficients (the readout is the same
        at every g): the error estimate's spread reads the whole surface, not the objective's
        nodes alone. None for the paper's layout (no basis)."""
        if self._readout is None:
            return None
        r = self._basis_all.shape[1]
        return self._basis_all.reshape(-1, 3, r)[np.asarray(nodes, np.int64)].reshape(-1, r)

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
            C = above_first(self._layers[-1][0], tape, np.float64) @ W1.astype(np.float64) + self._skip  # dc/dg (r, 3k)
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
                self._factors = GramFactors(self._layers[0][0], self._skip)
            if self._anchored is None:
                self._anchored = AnchoredGram(self._layers[-1][0], tape, self._factors)
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

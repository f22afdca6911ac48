"""A frame's outputs: the fields a session asks for at the frame's forces, its RMS distance, and
its error estimate with the spread that estimate reads (:mod:`.confidence`).

The spread's once-per-operator work (a readout's Gram matrix, a force prior) is kept for the
session's last two operators: method auto's frames read the network's and its corrector's. A
network's whole field may be made on a spare core (:mod:`.spare`) while the spread is found, or
started at each of Levenberg-Marquardt's trial points (:meth:`Outputs.prefetch`).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from .. import spare
from ..fem.assembly import Assembler
from ..fem.material import NeoHookean
from ..forward import ForwardFailed, ForwardModel, ForwardOperator
from ..mesh import TetMesh
from .confidence import error_estimate, estimator_for, force_prior, inverse_spread, prior_windows
from .distance import PointToSurface
from .engine import FrameSolution

Array = np.ndarray


@dataclasses.dataclass
class FrameResult:
    frame_id: int | str | None
    converged: bool
    status: str
    objective: float
    distance_rms: float
    iterations: int
    evaluations: int
    net_force: Array  # (3,)
    timing_ms: dict[str, float]
    support: Array  # (k,) the node ids the forces are aligned with
    outputs: dict[str, Array]  # only the requested ones
    alpha: float  # the regularisation weight this frame ran with
    error_estimate: float  # m, estimated mean nodal error of the displacement (confidence.py)
    method_used: str  # "network" or "fem": which forward model produced this frame
    message: str = ""


def von_mises(mesh: TetMesh, material: NeoHookean, u: Array) -> Array:
    """Von Mises equivalent of the Cauchy stress per tet, Pa. Shape: u (n, 3) -> (t,)."""
    sigma = material.cauchy(Assembler(mesh, material).F(u))
    dev = sigma - np.trace(sigma, axis1=1, axis2=2)[:, None, None] * np.eye(3) / 3.0
    return np.sqrt(1.5 * np.einsum("tij,tij->t", dev, dev))


def non_finite(sol: FrameSolution) -> FrameSolution:
    """A frame whose field folds elements: its residual, so its estimate, is infinite (API.md:
    never as converged; a failed frame leaves the warm start as it was)."""
    message = "the registered displacement inverts elements: its Neo-Hookean residual is infinite"
    return dataclasses.replace(sol, converged=False, status="non_finite", message=message)


class Outputs:
    """A session's frame outputs, on the support it last moved to (:meth:`move`). Not
    thread-safe: the session's lock serialises its frames."""

    def __init__(
        self,
        model: ForwardModel,
        distance: PointToSurface,
        want: tuple[str, ...],
        noise: float | None,
        max_force: float | None,
    ) -> None:
        """`want`: the outputs asked for; `noise` (m) and `max_force` (N): the estimate's
        inverse-problem term, with the declared noise or the model's force prior."""
        self.model = model
        self.mesh = model.mesh
        self.distance = distance
        self._want = set(want)
        self._rest = self.mesh.nodes[distance.nodes]
        self._noise = noise
        self._max_force = max_force
        self.spreads = bool(noise or max_force)
        # the spread reads the whole surface (confidence.py): the surface nodes the objective does not
        self._unread = np.setdiff1d(self.mesh.surface_nodes, distance.nodes)
        # (jac.U, U^T U) for inverse_spread, the latest first: auto's frames read two operators'
        self._readout_grams: list[tuple[Array, Array]] = []
        self._unread_grams: list[tuple[object, Array]] = []  # (op, the unread nodes' readout Gram)
        self._priors: list[tuple[object, Array]] = []  # (jac, force_prior), kept as the Grams
        self._early: tuple[Array, spare.Beside] | None = None  # (g, its field and forward error)
        # the estimate's rest factor and kernels' first use, made as the session opens: a first
        # frame has no reserve for them (0.25-1.8 s past its budget on the loaded phantom)
        rest = np.zeros((self.mesh.n_nodes, 3))
        estimator_for(model).forward_error(rest, rest[:0], np.zeros(0, np.int64))

    def move(self, support: Array) -> None:
        """Outputs on a new support: the force prior's windows are made for it."""
        self.support = support
        self._windows = prior_windows(self.mesh.nodes[support], getattr(self.model, "tool_patch", None))

    def warm(self, op: ForwardOperator, corrector_op: ForwardOperator | None) -> None:
        """The spread's once-per-operator work (:meth:`spread`), made with the operator, not in
        a frame (whose time budget it would overrun): the Gram matrix of the network's readout
        (about 50 ms on the phantom), the Newton method's rest Jacobian and its Gram (3 solves
        per support node). The network's Jacobians are left to the frames: their anchor is the
        first one's point, and moving it moves answers at rounding level, which a noise-chosen
        alpha amplifies (the demo's force error 10.2 -> 13.8 %, docs/performance.md). Method
        auto's `corrector_op` where given: its rest Jacobian and Gram too."""
        if not self.spreads:
            return
        U = getattr(op, "readout", None)
        if U is None and not hasattr(op, "at_rest"):  # the Newton method's
            U = self._rest_basis(op)
        if U is not None:
            self._readout_gram(op, U)
        if corrector_op is not None:  # auto's first correction would form them in its frame
            U = self._rest_basis(corrector_op)
            if U is not None:
                self._readout_gram(corrector_op, U)

    def _rest_basis(self, op: ForwardOperator) -> Array | None:
        """The basis U of an operator's estimate Jacobian at rest (None if it has none)."""
        jac = getattr(op, "estimate_jacobian", lambda g: None)(np.zeros((self.support.size, 3)))
        return None if jac is None else jac.U

    def _readout_gram(self, op: ForwardOperator, U: Array) -> Array:
        """The Gram (float64) of the readout over the whole surface in the coefficients of a
        Jacobian of `op` with basis U: U^T U, plus the Gram of the surface nodes the objective
        does not read (`op.readout_at`, at rest for the Newton method), each kept for the
        session's last two operators (the network's and, for method auto, its corrector's)."""

        def gram() -> Array:
            U64 = np.asarray(U, np.float64)
            return U64.T @ U64

        G = _last_two(self._readout_grams, U, gram)
        if not self._unread.size:  # the objective reads the whole surface (no `matching`)
            return G

        def unread() -> Array:
            V = np.asarray(op.readout_at(self._unread), np.float64)  # type: ignore[attr-defined]
            return V.T @ V

        return G + _last_two(self._unread_grams, op, unread)

    def _force_prior(self, jac) -> Array:
        """confidence.force_prior of a Jacobian, kept for the last two: the estimate Jacobians
        (at rest, without noise) are the operators' own, so it is made once per operator."""
        assert self._max_force is not None
        max_force = self._max_force
        return _last_two(self._priors, jac, lambda: force_prior(jac, self._windows, self.support.size, max_force))

    def of(
        self, op: ForwardOperator, model: ForwardModel, sol: FrameSolution, alpha: float, spare_core: bool
    ) -> tuple[dict[str, Array], float, float, float | None]:
        """The requested fields at the frame's forces `sol.g`, the RMS point-to-surface distance
        (the solve's at g, or searched for if it has none: the best iterate was never evaluated),
        the error estimate (the whole field is read for it, requested or not), and the force
        directions the cloud determined (:meth:`spread`'s gamma; None if not made).
        `spare_core`: whether `op` is the session's own and may make its field on a spare core
        (it offers a warm frame's rest state there: the network's), not method auto's corrector."""
        g, rms = sol.g, sol.rms
        gamma = None
        want = self._want
        out: dict[str, Array] = {}
        # with noise declared or a force prior, the network's field is made on a spare core (its
        # operator allows it, as for a warm frame's rest state) while this one finds the spread
        beside = spare_core and self.spreads and sol.u is not None
        early, self._early = self._early, None
        if early is not None and spare_core and np.array_equal(early[0], g):
            field = early[1]
        else:
            if early is not None:
                early[1].drop()
            field = spare.Beside(functools.partial(_field, op, model, g, self.support)) if beside else None
        spread = None
        if field is not None and sol.u is not None:
            spread, gamma = self.spread(op, g, self._rest + sol.u, alpha, sol.status)
        u_all, forward = field.result() if field is not None else _field(op, model, g, self.support)
        finite = u_all is not None and bool(np.isfinite(u_all).all())
        if not np.isfinite(rms) and (finite or u_all is None):  # a field not finite has no distance
            u_nodes = np.zeros((self.distance.nodes.size, 3)) if u_all is None else u_all[self.distance.nodes]
            rms = float(np.sqrt(np.mean(self.distance.closest(self._rest + u_nodes).sq_distances)))
        estimate = float("inf")
        if finite:
            if spread is None:
                x = self._rest + (u_all[self.distance.nodes] if sol.u is None else sol.u)
                spread, gamma = self.spread(op, g, x, alpha, sol.status)
            estimate = error_estimate(forward, rms, self._noise, spread)
            if "displacement" in want:
                out["displacement"] = u_all
            if "surface_displacement" in want:
                out["surface_displacement"] = u_all[self.mesh.surface_nodes]
            if "stress" in want:
                out["stress"] = von_mises(self.mesh, model.material, u_all)
        if "forces" in want:
            out["forces"] = g
        return out, rms, estimate, gamma

    def prefetch(self, op: ForwardOperator, g: Array) -> None:
        """Starts :func:`_field` at an evaluation's forces on a spare core, in place of the last
        one started (dropped if no thread has begun it)."""
        if self._early is not None:
            self._early[1].drop()
        g = np.array(g, np.float64)
        self._early = (g, spare.Beside(functools.partial(_field, op, self.model, g, self.support)))

    def spread(
        self, op: ForwardOperator, g: Array, x: Array, alpha: float, status: str = "converged"
    ) -> tuple[float, float | None]:
        """What the cloud leaves uncertain (confidence.inverse_spread: the declared noise, the
        force directions it does not determine under the model's force prior, the step left)
        and, with noise, the force directions it determined, at the matching nodes at x (p, 3).
        With noise declared, through the Jacobian at g (the noise's covariance and alpha's rule
        are taken there; the Newton method's costs 3 solves per support node, unless its last
        step made it there); without, or on a frame out of time (`status`), through the
        operator's estimate Jacobian (at rest; the Newton method's made with the operator:
        :meth:`warm`; past MAX_JACOBIAN_SUPPORT support nodes its leading directions,
        with or without noise). (0, None) with neither noise nor prior, or no Jacobian (the
        paper's layout)."""
        # the Newton method past MAX_JACOBIAN_SUPPORT has no Jacobian at g: its rest one's leading directions
        exact = self._noise and status != "time_limit" and getattr(op, "has_jacobian", True)
        jacobian = getattr(op, "jacobian" if exact else "estimate_jacobian", None)
        if not self.spreads or jacobian is None:
            return 0.0, None
        try:
            jac = jacobian(g)
        except ForwardFailed:  # g's equilibrium could not be solved again: the field is none either
            return float("inf"), None
        if jac is None:
            return 0.0, None
        match = self.distance.last_match
        if match is None or not np.array_equal(match.x, x):  # the answer was not the last evaluation
            self.distance(x)
            match = self.distance.last_match
        Cg = jac.matvec(np.asarray(g, np.float64).ravel())
        prior = None if not self._max_force else self._force_prior(jac)
        spread, gamma = inverse_spread(
            jac,
            match,
            self.distance.faces,
            alpha,
            self._noise or 0.0,
            self._readout_gram(op, jac.U),
            Cg,
            prior,
            readout_nodes=self.distance.nodes.size + self._unread.size,
        )
        return spread, gamma if self._noise else None


def _last_two(kept: list, key, make):
    """What `make()` gives for `key` (an object, matched by identity), from `kept`: the last two
    made, the latest first, held with their keys (so an identity cannot be reused)."""
    for i, (k, value) in enumerate(kept):
        if k is key:
            kept.insert(0, kept.pop(i))
            return value
    kept[:] = [(key, make()), *kept[:1]]
    return kept[0][1]


def _field(op: ForwardOperator, model: ForwardModel, g: Array, support: Array) -> tuple[Array | None, float]:
    """The whole displacement at g and its forward error (confidence.py): a frame's costly
    outputs. (None, inf) where the field cannot be recomputed; its error inf where not finite."""
    try:
        u_all = op.displacement(g)
    except ForwardFailed:  # the best iterate's field could not be recomputed: no NaN
        return None, math.inf
    if not np.isfinite(u_all).all():
        return u_all, math.inf
    return u_all, estimator_for(model).forward_error(u_all, g, support)

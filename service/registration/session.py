"""A registration stream: one model, one configuration, frames in order, warm-started.

A session keeps the previous frame's forces and starts the next frame's L-BFGS-B from them. A
support change maps those forces onto the new support (nodes in both keep theirs, new nodes
start at zero) and rebuilds the restricted operator. A frame that fails (the forward model
diverged, or something was not finite) returns its best iterate with ``converged: false`` and
leaves the warm start exactly as it was; a frame that merely ran out of iterations still moves
the warm start to its best iterate, which is better than where it began, but the next frame also
tries the last converged frame's forces and starts from the better of the two (a cloud that was
garbage, metres off say, costs one evaluation, not the frames after it), and only
converged frames teach the carried curvature. A cloud past the model's reach (:mod:`.reach`: in
millimetres against metres, say) is refused before anything changes.

A session told its clouds' noise moves alpha after every frame that did not fail
(:mod:`.noise_prior`), and shifts the carried curvature by the same amount.

Only the outputs the session asks for are computed: the optimisation itself reads the
displacement of the matching surface's nodes alone. A network session with Levenberg-Marquardt
starts the whole field and its error estimate at each trial point on a spare core (the answer
is the last accepted one), and evaluates each warm frame's rest state there too (:mod:`.spare`).
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import math
import statistics
import threading
import time

import numpy as np

from .. import spare
from ..fem.assembly import Assembler
from ..fem.material import NeoHookean
from ..forward import ForwardFailed, ForwardModel, ForwardOperator, check_support
from ..mesh import TetMesh
from .confidence import error_estimate, estimator_for, force_prior, inverse_spread, past_max_force, prior_windows
from .distance import PointToSurface
from .engine import FAILED, FrameSolution, SolveOptions, check_optimizer, solve_frame
from .noise_prior import AlphaTracker
from .precondition import Curvature
from .reach import Box, check_reach
from .settings import DEFAULT_ALPHA, DEFAULT_GTOL, METHODS, OUTPUT_NAMES, SessionConfig

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


def _non_finite(sol: FrameSolution) -> FrameSolution:
    """A frame whose field folds elements: its residual, so its estimate, is infinite (API.md:
    never as converged; a failed frame leaves the warm start as it was)."""
    message = "the registered displacement inverts elements: its Neo-Hookean residual is infinite"
    return dataclasses.replace(sol, converged=False, status="non_finite", message=message)


def default_support(model: ForwardModel) -> Array:
    """Every node the model can put a force on: its load region, or the free surface."""
    region = getattr(model, "region", None)
    return np.asarray(region if region is not None else model.mesh.free_surface_nodes, np.int64)


def von_mises(mesh: TetMesh, material: NeoHookean, u: Array) -> Array:
    """Von Mises equivalent of the Cauchy stress per tet, Pa. Shape: u (n, 3) -> (t,)."""
    sigma = material.cauchy(Assembler(mesh, material).F(u))
    dev = sigma - np.trace(sigma, axis1=1, axis2=2)[:, None, None] * np.eye(3) / 3.0
    return np.sqrt(1.5 * np.einsum("tij,tij->t", dev, dev))


class Session:
    """Frames of one stream, in order. Thread-safe: frames of one session never interleave."""

    def __init__(self, model: ForwardModel, config: SessionConfig, corrector: ForwardModel | None = None) -> None:
        """`model` answers the frames; `corrector` (the FEM, for method "auto") re-registers
        a frame whose error estimate exceeds the config's max_error."""
        if config.method not in METHODS:
            raise ValueError(f"unknown method {config.method!r}; choose from {list(METHODS)}")
        if config.method == "auto":
            if config.max_error is None:
                raise ValueError("method 'auto' needs max_error (m): the estimate past which the FEM corrects a frame")
            if corrector is None:
                raise ValueError("method 'auto' needs the FEM to correct with")
        elif config.max_error is not None:
            raise ValueError("max_error applies to method 'auto' only")
        E_model = float(model.material.E)
        if config.E is not None:
            model = model.with_stiffness(config.E)
            corrector = None if corrector is None else corrector.with_stiffness(config.E)
        self.corrector = corrector
        self._corrector_op: ForwardOperator | None = None
        unknown = set(config.outputs) - set(OUTPUT_NAMES)
        if unknown:
            raise ValueError(f"unknown outputs {sorted(unknown)}; choose from {list(OUTPUT_NAMES)}")
        self.model = model
        self.mesh = model.mesh
        faces = self.mesh.surface_faces if config.matching is None else check_faces(self.mesh, config.matching)
        self.distance = PointToSurface(faces, loss=config.loss, loss_param=config.loss_param)
        support = (
            default_support(model) if config.support is None else check_support(self.mesh, np.asarray(config.support))
        )
        gtol = config.gtol if config.gtol is not None else DEFAULT_GTOL.get(model.method, 1e-4)
        alpha = config.alpha if config.alpha is not None else DEFAULT_ALPHA * (E_model / float(model.material.E)) ** 2
        self.alpha_tracker: AlphaTracker | None = None
        # noise without alpha chooses alpha; a given alpha stays, and noise informs the estimate alone
        if config.noise is not None and config.alpha is None:
            if config.loss != "squared":
                raise ValueError(f"noise chooses alpha for the squared loss only, not {config.loss!r}")
            self.alpha_tracker = AlphaTracker(alpha, config.noise)  # starts at the default
        # the effective values echoed (API.md): the trimmed loss's default fraction too
        loss_param = {"huber": self.distance.delta, "trimmed": self.distance.trim}.get(config.loss)
        self.config = dataclasses.replace(
            config, E=float(model.material.E), gtol=gtol, alpha=alpha, loss_param=loss_param
        )
        self._noise = config.noise
        # the estimate's inverse-problem term: with declared noise or the model's force prior
        self._max_force: float | None = getattr(model, "max_force", None)
        self._spreads = bool(config.noise or self._max_force)
        # (jac.U, U^T U) for inverse_spread, the latest first: auto's frames read two operators'
        self._readout_grams: list[tuple[Array, Array]] = []
        self._priors: list[tuple[object, Array]] = []  # (jac, force_prior), kept as the Grams
        self._options = SolveOptions.of(self.config)
        # the same problem in scaled forces, as alpha: a softer organ's are smaller (x 1.0 at E_model)
        self._options = dataclasses.replace(
            self._options, force_scale=self._options.force_scale * (float(model.material.E) / E_model)
        )
        self._rest = self.mesh.nodes[self.distance.nodes]
        self._box = Box(self.mesh.nodes)  # how far off a cloud may lie (reach.py)
        self._lock = threading.Lock()
        self._set_support(support, None)
        # the same distance, only ever at rest: a warm frame's rest state evaluated beside its
        # start (engine.solve_frame), for operators that offer it (the network)
        self._rest_distance = (
            PointToSurface(faces, loss=config.loss, loss_param=config.loss_param, lone=True)
            if hasattr(self.op, "at_rest")
            else None
        )
        # Levenberg-Marquardt's answer is its last accepted evaluation: the network's outputs
        # for each loaded evaluation start on a spare core while its distance is measured
        self._early_outputs = self._rest_distance is not None and self._options.optimizer == "levenberg-marquardt"
        self._early: tuple[Array, spare.Beside] | None = None  # (g, its field and forward error)
        # seconds each of the last frames took after its solve (outputs, estimate, commit): the
        # room a time budget keeps for them (:meth:`_reserve`)
        self._after_solve: collections.deque[float] = collections.deque(maxlen=AFTER_SOLVE_FRAMES)
        self.frames = 0
        self.converged = 0
        self.failed = 0
        self.seconds = 0.0
        self.created = time.time()
        self.last_used = time.monotonic()

    def _set_support(self, support: Array, g_old: Array | None) -> None:
        """Move to a new support; its operator is made and checked first, so a support this
        session cannot take (a ValueError) changes nothing."""
        op = self.model.restrict(support, self.distance.nodes)
        check_optimizer(op, self._options)
        self.op = op
        self._corrector_op = None  # restricted again to the new support when next needed
        g = np.zeros((support.size, 3))
        if g_old is not None:
            old = {int(n): i for i, n in enumerate(self.support)}
            keep = np.array([old.get(int(n), -1) for n in support])
            g[keep >= 0] = g_old[keep[keep >= 0]]
        self.support = support
        self.g = g
        self._windows = prior_windows(self.mesh.nodes[support], getattr(self.model, "tool_patch", None))
        self._trend: Array | None = None  # the forces' change between the last two converged frames
        self._converged = False  # whether the last frame's answer converged
        self._trend_before: Array | None = None  # the trend one frame earlier
        self._before: tuple[Array, bool] = (g, False)  # the frame before's forces, and whether they did
        self._anchor = g  # the last converged frame's forces: a fallback start after a bad frame
        self.curvature = Curvature(3 * support.size) if self.config.carry_curvature else None
        # the corrector's frames teach their own: the FEM's curvature is not the network's
        self._corrector_curvature = Curvature(3 * support.size) if self.config.carry_curvature else None
        self._warm_spread(opening=g_old is None)

    def _warm_spread(self, opening: bool) -> None:
        """The spread's once-per-operator work (:meth:`_spread`), made with the operator, not in
        a frame (whose time budget it would overrun): the Gram matrix of the network's readout
        (about 50 ms on the phantom), the Newton method's rest Jacobian and its Gram (3 solves
        per support node). The network's Jacobians are left to the frames: their anchor is the
        first one's point, and moving it moves answers at rounding level, which a noise-chosen
        alpha amplifies (the demo's force error 10.2 -> 13.8 %, docs/performance.md). When the
        session opens (`opening`), method auto's corrector's rest Jacobian and Gram too: nearly
        every any-site auto session corrects, and its first correction had them to make inside
        its frame; a support change inside a frame leaves them to its first correction."""
        if not self._spreads:
            return
        U = getattr(self.op, "readout", None)
        if U is None and not hasattr(self.op, "at_rest"):  # the Newton method's
            U = self._rest_basis(self.op)
        if U is not None:
            self._readout_gram(U)
        if opening and self.corrector is not None:  # auto's first correction would form them in its frame
            self._corrector_op = self.corrector.restrict(self.support, self.distance.nodes)
            U = self._rest_basis(self._corrector_op)
            if U is not None:
                self._readout_gram(U)

    def _rest_basis(self, op: ForwardOperator) -> Array | None:
        """The basis U of an operator's estimate Jacobian at rest (None if it has none)."""
        jac = getattr(op, "estimate_jacobian", lambda g: None)(np.zeros((self.support.size, 3)))
        return None if jac is None else jac.U

    def _readout_gram(self, U: Array) -> Array:
        """U^T U (float64) of a Jacobian's basis U, kept for the session's last two (the
        network's and, for method auto, its corrector's): constant per operator."""

        def gram() -> Array:
            U64 = np.asarray(U, np.float64)
            return U64.T @ U64

        return _last_two(self._readout_grams, U, gram)

    def _force_prior(self, jac) -> Array:
        """confidence.force_prior of a Jacobian, kept for the last two: the estimate Jacobians
        (at rest, without noise) are the operators' own, so it is made once per operator."""
        assert self._max_force is not None
        max_force = self._max_force
        return _last_two(self._priors, jac, lambda: force_prior(jac, self._windows, self.support.size, max_force))

    def frame(self, points: Array, support: Array | None = None, frame_id=None) -> FrameResult:
        with self._lock, spare.frame():
            # the clock counts the input's checks (timing_ms "check": the reach's 3-6 ms at 100k points)
            t0 = time.perf_counter()
            points, support = self._checked(points, support)  # before any state: a refused frame changes nothing
            t_checked = time.perf_counter()
            self.last_used = time.monotonic()
            if support is not None and not np.array_equal(support, self.support):
                self._set_support(support, self.g)
            self.distance.bind(points)
            if self._rest_distance is not None:
                self._rest_distance.bind(points)
            g0, fallbacks = self._start()
            options = self._options
            if self.alpha_tracker is not None:
                options = dataclasses.replace(options, alpha=self.alpha_tracker.alpha)
            prefetch = self._prefetch if self._early_outputs else None
            reserve = self._reserve(options.time_budget) if options.time_budget is not None else 0.0
            deadline = None if options.time_budget is None else t0 + options.time_budget - reserve
            sol = solve_frame(
                self.op,
                self.distance,
                self._rest,
                g0,
                options,
                self.curvature,
                fallbacks,
                self._rest_distance,
                prefetch,
                deadline=deadline,
                box=self._box,
            )
            t1 = time.perf_counter()
            if sol.status == "time_limit" and reserve > 0.0:
                kept = f"{1e3 * reserve:.3g} ms of it kept for the outputs and the estimate after the solve"
                sol = dataclasses.replace(sol, message=f"{sol.message} ({kept})")
            # the outputs before the commit: a failed frame's commit forgets the operator's kept
            # equilibria, the best iterate's among them, and a solve from rest may not reach it
            outputs, rms, estimate, gamma = self._outputs(self.op, self.model, sol, options.alpha)
            if not np.isfinite(estimate) and sol.status not in FAILED:  # failed before it moves the warm start
                sol = _non_finite(sol)
            if self._commit(sol, learn=True):  # a noisy stream's alpha learns from what a frame starts from
                self._learn_alpha(sol.g, len(points), gamma)
            timing = sol.timing.as_ms()
            timing["check"] = 1e3 * (t_checked - t0)
            after = time.perf_counter() - t1
            timing["outputs"] = 1e3 * after
            if self.frames:  # a session's first frame pays one-time costs (kernels' first use)
                self._after_solve.append(after)
            method_used, iterations, evaluations = self.model.method, sol.iterations, sol.evaluations
            if self.config.method == "auto" and not estimate <= self.config.max_error:
                t2 = time.perf_counter()
                fem = self._correct(sol, options, fallbacks, deadline)
                fixed = None
                if fem.status not in FAILED:
                    fixed = self._outputs(self._corrector_op, self.corrector, fem, options.alpha)
                timing["correction"] = 1e3 * (time.perf_counter() - t2)
                # a converged correction stands (exact physics); one that did not converge only
                # where it estimates better: out of time before it reached the network's forces,
                # it is the rest state (a whole region's support, a spent budget), 3.5x worse
                if fixed is None or not (fem.converged or fixed[2] < estimate):  # the network's frame stands
                    self._corrector_op.reset()
                    if self._corrector_curvature is not None:
                        self._corrector_curvature.reset()
                else:
                    self._commit(fem, learn=False)
                    sol, method_used = fem, self.corrector.method
                    iterations, evaluations = iterations + fem.iterations, evaluations + fem.evaluations
                    outputs, rms, estimate, _ = fixed
            if not np.isfinite(estimate) and sol.status not in FAILED:  # API.md: never as converged
                sol = _non_finite(sol)
            converged, status, message = sol.converged, sol.status, sol.message
            timing["total"] = 1e3 * (time.perf_counter() - t0)
            self.frames += 1
            self.converged += int(converged)
            self.seconds += timing["total"] / 1e3
            return FrameResult(
                frame_id=frame_id,
                converged=converged,
                status=status,
                objective=sol.objective,
                distance_rms=rms,
                iterations=iterations,
                evaluations=evaluations,
                net_force=sol.g.sum(axis=0),
                timing_ms=timing,
                support=self.support,
                outputs=outputs,
                alpha=options.alpha,
                error_estimate=estimate,
                method_used=method_used,
                message=message,
            )

    def _checked(self, points, support) -> tuple[Array, Array | None]:
        """A frame's cloud as (m, 3) float64 and its support's node ids (None: the session's),
        or a one-line ValueError: a bad shape, a value not finite, a cloud past the model's reach
        (reach.py), a support this mesh cannot take."""
        points = np.asarray(points, np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
            raise ValueError(f"points must be a non-empty (m, 3) array, got shape {points.shape}")
        if not np.isfinite(points).all():
            raise ValueError("points contain NaN or infinite values")
        check_reach(self._box, points)
        return points, None if support is None else check_support(self.mesh, np.asarray(support))

    def _start(self) -> tuple[Array, tuple[Array, ...]]:
        """The frame's starting forces and the fallbacks worth an evaluation each: zero cold; warm,
        for the network, the last forces plus their last change where the last two frames
        converged (a tool moves steadily between frames: the optimizer starts nearer), alone
        where that change agrees with the one before (steady motion), else beside the last forces
        (on noisy clouds the change is noise: the engine starts from whichever fits the new
        cloud better); else the last forces, with the last converged frame's as a fallback."""
        if not self.config.warm_start:
            return np.zeros_like(self.g), ()
        # the Newton method keeps its start: at its gtol the prediction saved it no iterations
        # (any-site calibration sites, docs/performance.md), and a start no frame has reached
        # can fail its solve, which costs up to the solve's whole iteration budget
        if self.config.predict and self._trend is not None and self.model.method == "network":
            if self._trend_before is not None and _agree(self._trend, self._trend_before):
                return self.g + self._trend, ()  # the last two changes agree: the motion, not noise
            # the prediction evaluated last: where it wins, the optimiser's first Jacobian and
            # match are that evaluation's, not made again
            return self.g, (self.g + self._trend,)
        return self.g, (self._anchor,)

    def _reserve(self, budget: float) -> float:
        """Seconds of a frame's time `budget` kept for what follows its solve (the outputs, the
        error estimate, the commit): the median of what that took on the session's last
        AFTER_SOLVE_FRAMES frames, its first frame left out (it pays one-time costs, the first
        use of kernels and caches), 0 before there are any; so that the whole frame, not only
        its optimiser, fits in the budget where it can. The lower median, so that one slow frame
        among the first few is ridden out as among five (of two, the faster), and never past
        RESERVE_SHARE of the budget: a reserve past it left the solve no time, frame after frame."""
        if not self._after_solve:
            return 0.0
        return min(statistics.median_low(self._after_solve), RESERVE_SHARE * budget)

    def _commit(self, sol, learn: bool) -> bool:
        """Move the warm start to a frame's answer. A failed one leaves it as it was, and so does a
        network's first answer that did not converge past what it learned (API.md: a non-converged
        solve does not poison the warm start): a glitched cloud's unfinished forces led the next
        good frame to a converged answer 6.6x worse than a fresh session's.
        Other unfinished answers are progress (a time budget's frames continue each other).
        Whether it moved."""
        if sol.status in FAILED or (learn and not sol.converged and self._glitch(sol.g)):
            self.op.reset()
            if self.curvature is not None:
                self.curvature.reset()
            self.failed += int(learn and sol.status in FAILED)
            self._trend, self._converged = None, False
            return False
        if learn:  # a frame's first answer; the FEM's correction (learn False) replaces it
            self._before = (self.g, self._converged)
            self._trend_before = self._trend
        prior, prior_converged = self._before
        self._trend = sol.g - prior if (sol.converged and prior_converged) else None
        self._converged = sol.converged
        self.g = sol.g
        if sol.converged:
            self._anchor = sol.g
        return True

    def _glitch(self, g: Array) -> bool:
        """Whether a network's unfinished forces g lie past what it learned: a resultant past the
        model's largest tool force (at the session's E). Not the simulate's sum of nodal
        magnitudes: a whole region's regularised answer spreads small forces over hundreds of
        nodes, whose magnitudes sum past it where the tool's do not. The Newton method holds at
        any load: its unfinished frames are progress however hard the tool pulls."""
        return self.model.method == "network" and past_max_force(float(np.linalg.norm(g.sum(axis=0))), self._max_force)

    def _learn_alpha(self, g: Array, n_points: int, gamma: float | None) -> None:
        """Move a noisy stream's alpha after a frame's first answer g, with the force directions
        its cloud determined (`gamma`, from its estimate's noise term; None: all of them)."""
        if self.alpha_tracker is None:
            return
        before = self.alpha_tracker.alpha
        after = self.alpha_tracker.update(g, n_points, gamma)
        for curvature in (self.curvature, self._corrector_curvature):
            if curvature is not None:
                curvature.shift(after - before)

    def _correct(self, sol, options: SolveOptions, fallbacks: tuple, deadline: float | None):
        """The FEM's registration of the bound cloud, from the network's answer (or its start),
        until the frame's `deadline` (the network's), 1 ms at least."""
        if self._corrector_op is None:
            self._corrector_op = self.corrector.restrict(self.support, self.distance.nodes)
        # the session's optimizer where the FEM runs it for this support: Levenberg-Marquardt
        # forms the FEM's Jacobian once, then steps through its products (a few solves a step):
        # auto's frames 1.2-8x faster than with L-BFGS-B on calibration sites, the same error
        lm = options.optimizer == "levenberg-marquardt" and getattr(self._corrector_op, "has_jacobian", False)
        fem_options = dataclasses.replace(
            options,
            gtol=DEFAULT_GTOL[self.corrector.method],
            optimizer="levenberg-marquardt" if lm else "lbfgsb",
            precondition=False,
        )
        if deadline is not None:
            deadline = max(deadline, time.perf_counter() + 1e-3)
        start = self.g if sol.status in FAILED else sol.g
        return solve_frame(
            self._corrector_op,
            self.distance,
            self._rest,
            start,
            fem_options,
            self._corrector_curvature,
            fallbacks,
            deadline=deadline,
            box=self._box,
        )

    def _outputs(
        self, op: ForwardOperator, model: ForwardModel, sol: FrameSolution, alpha: float
    ) -> tuple[dict[str, Array], float, float, float | None]:
        """The requested fields at the frame's forces `sol.g`, the RMS point-to-surface distance
        (the solve's at g, or searched for if it has none: the best iterate was never evaluated),
        the error estimate (the whole field is read for it, requested or not), and the force
        directions the cloud determined (:meth:`_spread`'s gamma; None if not made)."""
        g, rms = sol.g, sol.rms
        gamma = None
        want = set(self.config.outputs)
        out: dict[str, Array] = {}
        # with noise declared or a force prior, the network's field is made on a spare core (its
        # operator allows it, as for a warm frame's rest state) while this one finds the spread
        beside = op is self.op and self._rest_distance is not None and self._spreads and sol.u is not None
        early, self._early = self._early, None
        if early is not None and op is self.op and np.array_equal(early[0], g):
            field = early[1]
        else:
            if early is not None:
                early[1].drop()
            field = spare.Beside(functools.partial(_field, op, model, g, self.support)) if beside else None
        spread = None
        if field is not None and sol.u is not None:
            spread, gamma = self._spread(op, g, self._rest + sol.u, alpha, sol.status)
        u_all, forward = field.result() if field is not None else _field(op, model, g, self.support)
        finite = u_all is not None and bool(np.isfinite(u_all).all())
        if not np.isfinite(rms) and (finite or u_all is None):  # a field not finite has no distance
            u_nodes = np.zeros((self.distance.nodes.size, 3)) if u_all is None else u_all[self.distance.nodes]
            rms = float(np.sqrt(np.mean(self.distance.closest(self._rest + u_nodes).sq_distances)))
        estimate = float("inf")
        if finite:
            if spread is None:
                x = self._rest + (u_all[self.distance.nodes] if sol.u is None else sol.u)
                spread, gamma = self._spread(op, g, x, alpha, sol.status)
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

    def _prefetch(self, g: Array) -> None:
        """Starts :func:`_field` at an evaluation's forces on a spare core, in place of the last
        one started (dropped if no thread has begun it)."""
        if self._early is not None:
            self._early[1].drop()
        g = np.array(g, np.float64)
        self._early = (g, spare.Beside(functools.partial(_field, self.op, self.model, g, self.support)))

    def _spread(
        self, op: ForwardOperator, g: Array, x: Array, alpha: float, status: str = "converged"
    ) -> tuple[float, float | None]:
        """What the cloud leaves uncertain (confidence.inverse_spread: the declared noise, the
        force directions it does not determine under the model's force prior, the step left)
        and, with noise, the force directions it determined, at the matching nodes at x (p, 3).
        With noise declared, through the Jacobian at g (the noise's covariance and alpha's rule
        are taken there; the Newton method's costs 3 solves per support node, unless its last
        step made it there); without, or on a frame out of time (`status`), through the
        operator's estimate Jacobian (at rest; the Newton method's made with the operator:
        :meth:`_warm_spread`; past MAX_JACOBIAN_SUPPORT support nodes its leading directions,
        with or without noise). (0, None) with neither noise nor prior, or no Jacobian (the
        paper's layout)."""
        # the Newton method past MAX_JACOBIAN_SUPPORT has no Jacobian at g: its rest one's leading directions
        exact = self._noise and status != "time_limit" and getattr(op, "has_jacobian", True)
        jacobian = getattr(op, "jacobian" if exact else "estimate_jacobian", None)
        if not self._spreads or jacobian is None:
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
            jac, match, self.distance.faces, alpha, self._noise or 0.0, self._readout_gram(jac.U), Cg, prior
        )
        return spread, gamma if self._noise else None

    def summary(self) -> dict:
        return {
            "frames": self.frames,
            "converged": self.converged,
            "failed": self.failed,
            "seconds": self.seconds,
            "support_size": int(self.support.size),
        }


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


def check_faces(mesh: TetMesh, faces) -> Array:
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError("matching must be a non-empty list of node-id triples")
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError("matching node ids must be integers")
    if f.min() < 0 or f.max() >= mesh.n_nodes:
        raise ValueError(f"matching node ids must lie in 0..{mesh.n_nodes - 1}")
    return f.astype(np.int64)


#: the frames whose time after the solve sizes the next one's reserve (:meth:`Session._reserve`):
#: their median rides out one slow frame (a collection, a busy core) without chasing it
AFTER_SOLVE_FRAMES = 5
#: the most of a time budget kept for what follows the solve: the solve keeps the rest. Outputs
#: slower than half the budget cannot fit beside a solve that makes progress, so past it the frame
#: overruns by their excess instead (review s24: one 1.3 s frame at a 150 ms budget left the next
#: frames 0 iterations, their forces frozen while the load grew)
RESERVE_SHARE = 0.5

#: the cosine above which two successive changes of the forces count as one steady motion
STEADY = 0.5


def _agree(a: Array, b: Array) -> bool:
    """Whether two changes of the forces point the same way (cosine above STEADY)."""
    na, nb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
    return na > 0 and nb > 0 and float(np.vdot(a, b)) > STEADY * na * nb

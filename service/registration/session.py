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

import dataclasses
import functools
import threading
import time

import numpy as np

from .. import spare
from ..forward import ForwardModel, ForwardOperator, check_support
from .confidence import past_max_force
from .distance import PointToSurface
from .engine import FAILED, SolveOptions, check_optimizer, solve_frame
from .inputs import check_config, check_faces, check_frame, default_support
from .noise_prior import AlphaTracker
from .outputs import FrameResult, Outputs, non_finite
from .precondition import Curvature
from .reach import Box
from .reserve import Reserve
from .settings import DEFAULT_ALPHA, DEFAULT_GTOL, SessionConfig

Array = np.ndarray


class Session:
    """Frames of one stream, in order. Thread-safe: frames of one session never interleave."""

    def __init__(self, model: ForwardModel, config: SessionConfig, corrector: ForwardModel | None = None) -> None:
        """`model` answers the frames; `corrector` (the FEM, for method "auto") re-registers
        a frame whose error estimate exceeds the config's max_error."""
        check_config(config, corrector)
        E_model = float(model.material.E)
        if config.E is not None:
            model = model.with_stiffness(config.E)
            corrector = None if corrector is None else corrector.with_stiffness(config.E)
        self.corrector = corrector
        self._corrector_op: ForwardOperator | None = None
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
        # the estimate's inverse-problem term: with declared noise or the model's force prior
        self._max_force: float | None = getattr(model, "max_force", None)
        self._outputs = Outputs(model, self.distance, config.outputs, config.noise, self._max_force)
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
        # the room a time budget keeps for what follows the solve (outputs, estimate, commit)
        self._reserve = Reserve()
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
        self._outputs.move(support)
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
        """The spread's once-per-operator work (:meth:`Outputs.warm`), made with the operator. When
        the session opens (`opening`), method auto's corrector's rest Jacobian and Gram too: nearly
        every any-site auto session corrects, and its first correction had them to make inside
        its frame; a support change inside a frame leaves them to its first correction."""
        if not self._outputs.spreads:
            return
        corrector_op = None
        if opening and self.corrector is not None:  # auto's first correction would form them in its frame
            self._corrector_op = corrector_op = self.corrector.restrict(self.support, self.distance.nodes)
        self._outputs.warm(self.op, corrector_op)

    def frame(self, points: Array, support: Array | None = None, frame_id=None) -> FrameResult:
        with self._lock, spare.frame():
            # the clock counts the input's checks (timing_ms "check": the reach's 3-6 ms at 100k points)
            t0 = time.perf_counter()
            points, support = check_frame(
                self.mesh, self._box, points, support
            )  # before any state: a refused frame changes nothing
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
            prefetch = functools.partial(self._outputs.prefetch, self.op) if self._early_outputs else None
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
            spare_core = self._rest_distance is not None
            outputs, rms, estimate, gamma = self._outputs.of(self.op, self.model, sol, options.alpha, spare_core)
            if not np.isfinite(estimate) and sol.status not in FAILED:  # failed before it moves the warm start
                sol = non_finite(sol)
            if self._commit(sol, learn=True):  # a noisy stream's alpha learns from what a frame starts from
                self._learn_alpha(sol.g, len(points), gamma)
            timing = sol.timing.as_ms()
            timing["check"] = 1e3 * (t_checked - t0)
            after = time.perf_counter() - t1
            timing["outputs"] = 1e3 * after
            if self.frames:  # a session's first frame pays one-time costs (kernels' first use)
                self._reserve.after_solve.append(after)
            method_used, iterations, evaluations = self.model.method, sol.iterations, sol.evaluations
            if self.config.method == "auto" and not estimate <= self.config.max_error:
                t2 = time.perf_counter()
                fem = self._correct(sol, options, fallbacks, deadline)
                fixed = None
                if fem.status not in FAILED:
                    fixed = self._outputs.of(self._corrector_op, self.corrector, fem, options.alpha, False)
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
                sol = non_finite(sol)
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

    def summary(self) -> dict:
        return {
            "frames": self.frames,
            "converged": self.converged,
            "failed": self.failed,
            "seconds": self.seconds,
            "support_size": int(self.support.size),
        }


#: the cosine above which two successive changes of the forces count as one steady motion
STEADY = 0.5


def _agree(a: Array, b: Array) -> bool:
    """Whether two changes of the forces point the same way (cosine above STEADY)."""
    na, nb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
    return na > 0 and nb > 0 and float(np.vdot(a, b)) > STEADY * na * nb

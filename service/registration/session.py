"""A registration stream: one model, one configuration, frames in order, warm-started.

A session keeps the previous frame's forces and starts the next frame's L-BFGS-B from them. A
support change maps those forces onto the new support (nodes in both keep theirs, new nodes
start at zero) and rebuilds the restricted operator. A frame that fails (the forward model
diverged, or something was not finite) returns its best iterate with ``converged: false`` and
leaves the warm start exactly as it was; a frame that merely ran out of iterations still moves
the warm start to its best iterate, which is better than where it began, but the next frame also
tries the last converged frame's forces and starts from the better of the two (a cloud that was
garbage, a kilometre away say, costs one evaluation, not the frames after it), and only
converged frames teach the carried curvature.

A session told its clouds' noise moves alpha after every frame that did not fail
(:mod:`.noise_prior`), and shifts the carried curvature by the same amount.

Only the outputs the session asks for are computed: the optimisation itself reads the
displacement of the matching surface's nodes alone.
"""

from __future__ import annotations

import dataclasses
import threading
import time

import numpy as np

from ..fem.assembly import Assembler
from ..fem.material import NeoHookean
from ..forward import ForwardFailed, ForwardModel, check_support
from ..mesh import TetMesh
from .distance import PointToSurface
from .engine import SolveOptions, check_optimizer, solve_frame
from .noise_prior import AlphaTracker
from .precondition import Curvature
from .settings import DEFAULT_ALPHA, DEFAULT_GTOL, OUTPUT_NAMES, SessionConfig

Array = np.ndarray

FAILED = ("forward_failed", "non_finite")


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
    message: str = ""


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

    def __init__(self, model: ForwardModel, config: SessionConfig) -> None:
        E_model = float(model.material.E)
        if config.E is not None:
            model = model.with_stiffness(config.E)
        unknown = set(config.outputs) - set(OUTPUT_NAMES)
        if unknown:
            raise ValueError(f"unknown outputs {sorted(unknown)}; choose from {list(OUTPUT_NAMES)}")
        self.model = model
        self.mesh = model.mesh
        faces = self.mesh.surface_faces if config.matching is None else _check_faces(self.mesh, config.matching)
        self.distance = PointToSurface(faces, loss=config.loss, loss_param=config.loss_param)
        support = default_support(model) if config.support is None else check_support(self.mesh, np.asarray(config.support))
        gtol = config.gtol if config.gtol is not None else DEFAULT_GTOL.get(model.method, 1e-4)
        alpha = config.alpha if config.alpha is not None else DEFAULT_ALPHA * (E_model / float(model.material.E)) ** 2
        self.alpha_tracker: AlphaTracker | None = None
        if config.noise is not None:
            if config.alpha is not None:
                raise ValueError("give alpha or noise, not both: noise chooses alpha frame by frame")
            if config.loss != "squared":
                raise ValueError(f"noise chooses alpha for the squared loss only, not {config.loss!r}")
            self.alpha_tracker = AlphaTracker(alpha, config.noise)  # starts at the default
        self.config = dataclasses.replace(config, E=float(model.material.E), gtol=gtol, alpha=alpha)
        self._options = SolveOptions.of(self.config)
        self._rest = self.mesh.nodes[self.distance.nodes]
        self._lock = threading.Lock()
        self._set_support(support, None)
        check_optimizer(self.op, self._options)
        self.frames = 0
        self.converged = 0
        self.failed = 0
        self.seconds = 0.0
        self.created = time.time()
        self.last_used = time.monotonic()

    def _set_support(self, support: Array, g_old: Array | None) -> None:
        self.op = self.model.restrict(support, self.distance.nodes)
        g = np.zeros((support.size, 3))
        if g_old is not None:
            old = {int(n): i for i, n in enumerate(self.support)}
            keep = np.array([old.get(int(n), -1) for n in support])
            g[keep >= 0] = g_old[keep[keep >= 0]]
        self.support = support
        self.g = g
        self._anchor = g  # the last converged frame's forces: a fallback start after a bad frame
        self.curvature = Curvature(3 * support.size) if self.config.carry_curvature else None

    def frame(self, points: Array, support: Array | None = None, frame_id=None) -> FrameResult:
        points = np.asarray(points, np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
            raise ValueError(f"points must be a non-empty (m, 3) array, got shape {points.shape}")
        if not np.isfinite(points).all():
            raise ValueError("points contain NaN or infinite values")
        with self._lock:
            self.last_used = time.monotonic()
            t0 = time.perf_counter()
            if support is not None:
                support = check_support(self.mesh, np.asarray(support))
                if not np.array_equal(support, self.support):
                    self._set_support(support, self.g)
            self.distance.bind(points)
            g0 = self.g if self.config.warm_start else np.zeros_like(self.g)
            fallbacks = (self._anchor,) if self.config.warm_start else ()
            options = self._options
            if self.alpha_tracker is not None:
                options = dataclasses.replace(options, alpha=self.alpha_tracker.alpha)
            sol = solve_frame(self.op, self.distance, self._rest, g0, options, self.curvature, fallbacks)
            t1 = time.perf_counter()
            if sol.status in FAILED:
                self.op.reset()
                if self.curvature is not None:
                    self.curvature.reset()
                self.failed += 1
            else:
                self.g = sol.g
                if sol.converged:
                    self._anchor = sol.g
                if self.alpha_tracker is not None:
                    before = self.alpha_tracker.alpha
                    after = self.alpha_tracker.update(sol.g, len(points))
                    if self.curvature is not None:
                        self.curvature.shift(after - before)
            outputs, rms = self._outputs(sol.g, sol.rms)
            timing = sol.timing.as_ms()
            timing["outputs"] = 1e3 * (time.perf_counter() - t1)
            timing["total"] = 1e3 * (time.perf_counter() - t0)
            self.frames += 1
            self.converged += int(sol.converged)
            self.seconds += timing["total"] / 1e3
            return FrameResult(
                frame_id=frame_id,
                converged=sol.converged,
                status=sol.status,
                objective=sol.objective,
                distance_rms=rms,
                iterations=sol.iterations,
                evaluations=sol.evaluations,
                net_force=sol.g.sum(axis=0),
                timing_ms=timing,
                support=self.support,
                outputs=outputs,
                alpha=options.alpha,
                message=sol.message,
            )

    def _outputs(self, g: Array, rms: float) -> tuple[dict[str, Array], float]:
        """The requested fields at the frame's forces, and the RMS point-to-surface distance
        (the solve's at g, or searched for if it has none: the best iterate was never evaluated)."""
        want = set(self.config.outputs)
        out: dict[str, Array] = {}
        u_all = u_nodes = None
        try:
            if want & {"displacement", "surface_displacement", "stress"}:
                u_all = self.op.displacement(g)
                u_nodes = u_all[self.distance.nodes]
            elif not np.isfinite(rms):
                u_nodes, _ = self.op(g)
        except ForwardFailed:  # the best iterate's field could not be recomputed: no NaN
            u_all = u_nodes = None
        if not np.isfinite(rms):
            if u_nodes is None:
                u_nodes = np.zeros((self.distance.nodes.size, 3))
            rms = float(np.sqrt(np.mean(self.distance.closest(self._rest + u_nodes).sq_distances)))
        if u_all is not None:
            if "displacement" in want:
                out["displacement"] = u_all
            if "surface_displacement" in want:
                out["surface_displacement"] = u_all[self.mesh.surface_nodes]
            if "stress" in want:
                out["stress"] = von_mises(self.mesh, self.model.material, u_all)
        if "forces" in want:
            out["forces"] = g
        return out, rms

    def summary(self) -> dict:
        return {
            "frames": self.frames,
            "converged": self.converged,
            "failed": self.failed,
            "seconds": self.seconds,
            "support_size": int(self.support.size),
        }


def _check_faces(mesh: TetMesh, faces) -> Array:
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError("matching must be a non-empty list of node-id triples")
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError("matching node ids must be integers")
    if f.min() < 0 or f.max() >= mesh.n_nodes:
        raise ValueError(f"matching node ids must lie in 0..{mesh.n_nodes - 1}")
    return f.astype(np.int64)

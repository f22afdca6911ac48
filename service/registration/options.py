"""How one frame is solved (:class:`SolveOptions`), and the check that an operator can run the
optimizer they ask for, made once when a session opens and again at a frame's first use."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..forward import ForwardOperator
from .levenberg import prepare
from .settings import DEFAULT_ALPHA, DEFAULT_GTOL, NAMES, OPTIMIZERS, Optimizer, SessionConfig

Array = np.ndarray


@dataclasses.dataclass(frozen=True)
class SolveOptions:
    """How one frame is solved. A session's settings of the same name pass through
    (:meth:`of`); the rest are the engine's own."""

    alpha: float = DEFAULT_ALPHA  # regularisation weight on |g|^2 (m^2 / N^2, with J in m^2)
    gtol: float = DEFAULT_GTOL["fem"]
    max_iter: int = 100
    force_bound: float | None = None  # |g_i| <= bound per component, newtons
    force_scale: float = 0.1  # N: the optimiser's unit when the model gives no Jacobian
    precondition: bool = False  # damped Gauss-Newton preconditioning from the rest Jacobian
    # (precondition.py) where no carried curvature applies: a third of the beam's iterations
    # from rest; on the liver's partial clouds it costs time and force accuracy, so opt-in
    max_evaluations: int | None = None  # the optimiser's, past the starts'; default: 3 x max_iter
    max_failures: int = 4  # forward failures at trial points before the frame gives up
    time_budget: float | None = None  # seconds: past it the frame returns its best iterate
    # (status time_limit); a display wants a frame in time more than a last digit. A session
    # passes solve_frame a deadline inside it that leaves room for the frame's outputs
    optimizer: Optimizer = SessionConfig.optimizer  # or "levenberg-marquardt" (levenberg.py): no
    # bounds, and a model with a Jacobian (the reduced network); for whole-surface cold starts
    damping: float = 0.1  # Levenberg-Marquardt's first damping, in units of the mean curvature
    # the model sees (the beam: 0.1 lands every case at the L-BFGS-B error; 0.01 lands some in
    # a wrong basin from rest, 0.22 against 0.11 mm mean TRE)

    @classmethod
    def of(cls, config: SessionConfig) -> SolveOptions:
        """The options a session's settings give (per-model defaults already filled in)."""
        given = {f.name: getattr(config, f.name) for f in dataclasses.fields(cls) if f.name in NAMES}
        budget = config.time_budget_ms
        return cls(**given, time_budget=None if budget is None else 1e-3 * budget)


_BOUNDED = "levenberg-marquardt takes no force bounds: use optimizer 'lbfgsb'"
_NO_JACOBIAN = (
    "levenberg-marquardt needs a forward model with a Jacobian: the fem method, or the network method "
    "with a reduced surrogate (a Jacobian in its basis); use optimizer 'lbfgsb'"
)


def check_optimizer(op: ForwardOperator, options: SolveOptions) -> None:
    """Refuse, saying why, an optimizer this operator and these options cannot run (a session
    checks once, when it opens; solve_frame refuses the same at first use), and ready what it
    will run (Levenberg-Marquardt's compiled kernel), so that no frame's clock pays for it."""
    if options.optimizer not in OPTIMIZERS:
        raise ValueError(f"optimizer must be one of {list(OPTIMIZERS)}, got {options.optimizer!r}")
    refuse_bounds(options)
    if options.optimizer == "levenberg-marquardt":
        jacobian_of(op, np.zeros((len(op.support), 3)))
        prepare()  # its compiled kernel, before any frame's clock runs


def refuse_bounds(options: SolveOptions) -> None:
    """Levenberg-Marquardt takes no force bounds: refused by a session when it opens and by
    solve_frame before any evaluation."""
    if options.optimizer == "levenberg-marquardt" and options.force_bound is not None:
        raise ValueError(_BOUNDED)


def jacobian_of(op, g: Array):
    """The operator's Jacobian at g (levenberg.py's model input); ValueError if it has none."""
    jacobian = getattr(op, "jacobian", None)
    jac = None if jacobian is None else jacobian(g)
    if jac is None:
        raise ValueError(_NO_JACOBIAN)
    return jac

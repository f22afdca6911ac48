"""A session's settings, defined once: names, choices, defaults, bounds and what each is for.

:class:`SessionConfig` is the one list. The engine runs on it (:mod:`.session`); the API's
request schema, its echo of the effective config, and the fields the API hands over are built
from its fields (``service/api/schemas/sessions.py``, ``service/api/work.py``), so a new setting is one
line here plus the code that reads it.

Each field is declared with :func:`setting`: its default, a line for the API's documentation,
the bounds a request must keep (pydantic ``Field`` keywords), and ``per_model=True`` where the
default depends on the model or method (left ``None`` here, filled in when a session opens and
echoed back). In a request a number or switch may be null, meaning its default; a choice may
not.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal, get_args

ForwardMethod = Literal["network", "fem"]  # a forward model
Method = Literal["network", "fem", "auto"]  # auto: the network, corrected by the FEM past max_error
OutputName = Literal["displacement", "surface_displacement", "forces", "stress"]
Loss = Literal["squared", "huber", "trimmed"]
Optimizer = Literal["lbfgsb", "levenberg-marquardt"]
NodeList = tuple[int, ...]  # node ids
FaceList = tuple[tuple[int, int, int], ...]  # triangles as node-id triples
Outputs = tuple[OutputName, ...]

METHODS: tuple[str, ...] = get_args(Method)
OUTPUT_NAMES: tuple[str, ...] = get_args(OutputName)
LOSSES: tuple[str, ...] = get_args(Loss)
OPTIMIZERS: tuple[str, ...] = get_args(Optimizer)

#: the relative gradient tolerance per method, read off the error-against-time chart on the
#: paper's liver: the network's meets 20 ms a frame, the Newton method's 1 % force error
#: (docs/performance.md)
DEFAULT_GTOL = {"network": 3e-4, "fem": 1e-4}
#: the regularisation weight (m^2 / N^2) at the model's own stiffness; at another E it scales by
#: (E_model / E)^2, since u(g; E) = u(g E_model / E; E_model): the same problem in scaled forces
DEFAULT_ALPHA = 1e-7


def setting(default: Any = None, doc: str = "", *, per_model: bool = False, **bounds: Any) -> Any:
    """A field of :class:`SessionConfig`: its default, its documentation, the API's bounds."""
    meta = {"doc": doc, "per_model": per_model, "bounds": bounds}
    if isinstance(default, (list, dict, set)):
        raise TypeError("a setting's default must be immutable (a tuple, not a list)")
    return dataclasses.field(default=default, metadata=meta)


@dataclasses.dataclass(frozen=True)
class SessionConfig:
    """Every setting of a stream, defaults filled in (what the API echoes back)."""

    method: Method = setting(
        "network",
        "forward model: the trained network, the FEM (Newton adjoint), or auto: the network, with "
        "a frame whose error_estimate exceeds max_error registered again by the FEM (method_used "
        "says which)",
    )
    max_error: float | None = setting(
        None, "auto only: the error estimate (m) past which the FEM corrects a frame", gt=0, le=1
    )
    support: NodeList | None = setting(
        None, "node ids where forces may act (default: the model's load region)", per_model=True
    )
    alpha: float | None = setting(
        None,
        "regularisation weight on |g|^2 (default: 1e-7 at the model's E, x (E_model / E)^2 at another E); "
        "one so large that no force can lower the objective measurably ends each frame at the rest "
        "state, status converged, its message saying so",
        per_model=True,
        gt=0,
    )
    gtol: float | None = setting(
        None,
        "relative tolerance on the projected gradient (default: 3e-4 for the network, 1e-4 for the FEM)",
        per_model=True,
        gt=0,
        le=1,
    )
    # no upper bound here: the server's cap (/health's limits.max_iter) is the one, and says so
    max_iter: int = setting(200, "L-BFGS-B iterations per frame (at most the server's cap)", ge=1)
    force_bound: float | None = setting(None, "bound on each force component, N (none by default)", gt=0)
    time_budget_ms: float | None = setting(
        None,
        "per frame: bounds the frame as timing_ms.total counts it (from the session taking it, its "
        "checks included, to its result; not the queue, decoding or encoding): the optimiser begins no evaluation "
        "that would end past the budget less what the outputs and the error estimate took on the "
        "session's last frames (at most half the budget), and returns its best iterate with status "
        "time_limit. Nothing asked for is dropped: a frame takes at least its start's evaluations "
        "and its outputs",
        gt=0,
        le=3_600_000,
    )
    noise: float | None = setting(
        None,
        "per-axis noise of the clouds, m: the error estimate carries it into the answer instead "
        "of counting it as misfit; without alpha, alpha also follows the forces' MAP estimate frame "
        "by frame, sigma^2 / (points x mean force^2), from its default up to 100x it (each frame's "
        "result says its alpha; squared loss); with alpha, alpha stays",
        gt=0,
        le=1,
    )
    matching: FaceList | None = setting(
        None, "triangles the points may lie on (default: the whole boundary)", per_model=True
    )
    outputs: Outputs = setting(("displacement", "forces"), "fields each frame result carries", max_length=4)
    warm_start: bool = setting(True, "start each frame from the previous frame's forces")
    predict: bool = setting(
        True,
        "warm starts of the network: start from the previous frame's forces plus their change since "
        "the frame before (when both converged), as a tool moves steadily from frame to frame; where "
        "the change disagrees with the one before, the previous forces are tried beside it; false: "
        "the previous frame's forces as they are (the fem method always starts there)",
    )
    E: float | None = setting(None, "Young's modulus for this session, Pa (default: the model's)", per_model=True, gt=0)
    loss: Loss = setting("squared", "point-to-surface loss")
    loss_param: float | None = setting(None, "huber: threshold (length, m); trimmed: fraction ignored", gt=0, le=1.0)
    carry_curvature: bool = setting(
        True,
        "precondition each frame with the curvature the previous frames measured (unbounded solves)",
    )
    precondition: bool = setting(
        False,
        "Gauss-Newton preconditioning from the rest Jacobian for frames that start cold "
        "(whole-surface clouds; off by default)",
    )
    optimizer: Optimizer = setting(
        "lbfgsb",
        "lbfgsb (the default, the paper's), or levenberg-marquardt: Gauss-Newton steps through the "
        "model's Jacobian, fewer evaluations (whole-surface cold starts with the network; the fem "
        "method on supports up to 500 nodes, 3 solves a node a step); no force_bound",
    )


SETTINGS: tuple[dataclasses.Field, ...] = dataclasses.fields(SessionConfig)
NAMES: tuple[str, ...] = tuple(f.name for f in SETTINGS)

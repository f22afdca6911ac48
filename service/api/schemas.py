"""The API's bodies as pydantic models: what a request may hold, and what a reply holds.

Requests are validated strictly (no "5" for 5, no 5.0 for a node id, no unknown keys): a body
that does not fit is a 422 whose ``detail`` names the field and what is wrong. Arrays arrive as
nested lists (JSON or MessagePack) or packed arrays (MessagePack, see :mod:`.codec`) and leave
validation as NumPy arrays: one ``np.asarray`` per array, checked for shape, dtype and
finiteness, never an element at a time.

Reply models document the replies (``/docs``, ``/openapi.json``) and let tests check them; the
routes encode replies directly (arrays as packed bytes or lists) rather than through them, so a
large displacement field does not pass through pydantic.
"""

from __future__ import annotations

import dataclasses
import types
from typing import Annotated, Any, Literal, Union, get_args, get_origin, get_type_hints

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PlainValidator,
    ValidationError,
    WithJsonSchema,
    create_model,
    field_validator,
    model_validator,
)

from ..registration.settings import (
    OUTPUT_NAMES,  # noqa: F401 (the API's name for them)
    SETTINGS,
    FaceList,
    ForwardMethod,
    NodeList,
    OutputName,
    Outputs,
    SessionConfig,
)

INT64 = 2**63 - 1


class TooManyPoints(ValueError):
    """A cloud over the configured limit (HTTP 413, not 422: the body is valid, just too big)."""


# -- arrays --------------------------------------------------------------------------------------


def _array(v: Any, what: str) -> np.ndarray:
    """One np.asarray: numbers only (no strings, booleans, None, ragged lists, objects)."""
    if isinstance(v, np.ndarray):
        a = v
    elif isinstance(v, list):
        try:
            a = np.asarray(v)
        except (ValueError, TypeError, OverflowError):
            raise ValueError(f"{what} must be a regular array of numbers (not ragged, no nulls)") from None
    else:
        raise ValueError(f"{what} must be an array (nested lists, or a packed array in MessagePack)")
    if a.dtype.kind not in "iuf":
        raise ValueError(
            f"{what} must hold numbers, not booleans" if a.dtype.kind == "b" else f"{what} must hold numbers only"
        )
    if not a.flags.writeable:  # a packed array views the message's bytes: the engine gets its own
        a = a.copy()
    return a


def _vectors(v: Any, what: str, *, empty: bool = False) -> np.ndarray:
    a = _array(v, what)
    if a.ndim != 2 or a.shape[1] != 3 or (a.shape[0] == 0 and not empty):
        raise ValueError(f"{what} must be a non-empty (m, 3) array, got shape {list(a.shape)}")
    a = a.astype(np.float64, copy=False)
    if not np.isfinite(a).all():
        raise ValueError(f"{what} contain NaN or infinite values")
    return a


def _points(v: Any) -> np.ndarray:
    return _vectors(v, "points")


def _force_values(v: Any) -> np.ndarray:
    return _vectors(v, "force values")


def _no_booleans(v: Any, what: str, depth: int) -> None:
    """JSON true and false are no node ids: NumPy would read a list mixing them with numbers
    as 1 and 0 (nested lists: `depth` levels)."""
    rows = [v] if depth == 1 else v
    if isinstance(v, list) and any(isinstance(x, bool) for row in rows if isinstance(row, list) for x in row):
        raise ValueError(f"{what} must be integers, not booleans")


def _node_ids(v: Any) -> np.ndarray:
    _no_booleans(v, "node ids", 1)
    a = _array(v, "node ids")
    if a.ndim != 1 or a.size == 0:
        raise ValueError(f"node ids must be a non-empty flat list, got shape {list(a.shape)}")
    if a.dtype.kind == "f":
        raise ValueError("node ids must be integers")
    if a.dtype.kind == "u" and a.max() > INT64:
        raise ValueError("node ids must be non-negative integers below 2**63")
    a = a.astype(np.int64, copy=False)
    if a.min() < 0:
        raise ValueError("node ids must be non-negative integers")
    return a


def _triangles(v: Any) -> np.ndarray:
    _no_booleans(v, "matching node ids", 2)
    a = _array(v, "matching")
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] == 0:
        raise ValueError(f"matching must be a non-empty list of node-id triples, got shape {list(a.shape)}")
    if a.dtype.kind == "f":
        raise ValueError("matching node ids must be integers")
    if a.dtype.kind == "u" and a.max() > INT64:
        raise ValueError("matching node ids must be non-negative integers below 2**63")
    a = a.astype(np.int64, copy=False)
    if a.min() < 0:
        raise ValueError("matching node ids must be non-negative integers")
    return a


_VEC3 = {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}
Points = Annotated[
    np.ndarray,
    PlainValidator(_points),
    WithJsonSchema({"type": "array", "items": _VEC3, "minItems": 1, "description": "(m, 3) finite coordinates"}),
]
ForceValues = Annotated[
    np.ndarray,
    PlainValidator(_force_values),
    WithJsonSchema({"type": "array", "items": _VEC3, "minItems": 1, "description": "(k, 3) newtons"}),
]
NodeIds = Annotated[
    np.ndarray,
    PlainValidator(_node_ids),
    WithJsonSchema({"type": "array", "items": {"type": "integer", "minimum": 0}, "minItems": 1}),
]
Triangles = Annotated[
    np.ndarray,
    PlainValidator(_triangles),
    WithJsonSchema(
        {
            "type": "array",
            "items": {"type": "array", "items": {"type": "integer", "minimum": 0}, "minItems": 3, "maxItems": 3},
            "minItems": 1,
        }
    ),
]
FrameId = Annotated[int, Field(ge=-INT64 - 1, le=INT64)] | Annotated[str, Field(max_length=256)]
Finite = Annotated[float, Field(allow_inf_nan=False)]


class _Request(BaseModel):
    model_config = ConfigDict(strict=True, extra="forbid", arbitrary_types_allowed=True)


# -- requests ------------------------------------------------------------------------------------


def _request_field(f: dataclasses.Field, hint: Any) -> tuple[Any, Any]:
    """A setting as a request field: its API type, nullable for numbers and switches (null: the
    default), its bounds and documentation from the setting."""
    meta = f.metadata
    base = _API_TYPES.get(_strip_none(hint), hint)
    choice = get_origin(base) is Literal or base is _API_TYPES[Outputs]
    kind = base if choice else base | None
    kw = dict(meta["bounds"], description=meta["doc"])
    if f.name == "outputs":
        return kind, Field(default_factory=lambda: list(SessionConfig.outputs), **kw)
    return kind, Field(f.default, **kw)


def _reply_field(f: dataclasses.Field, hint: Any) -> Any:
    """A setting as the echo gives it: its effective value (per-model defaults filled in)."""
    base = _strip_none(hint) if f.metadata["per_model"] else hint
    return _REPLY_TYPES.get(base, base)


def _strip_none(hint: Any) -> Any:
    args = [a for a in get_args(hint) if a is not type(None)]
    return args[0] if get_origin(hint) in (Union, types.UnionType) and len(args) == 1 else hint


_HINTS = get_type_hints(SessionConfig)
_API_TYPES = {float: Finite, NodeList: NodeIds, FaceList: Triangles, Outputs: list[OutputName]}

_REQUEST_FIELDS: dict[str, Any] = {f.name: _request_field(f, _HINTS[f.name]) for f in SETTINGS}
#: typed Any: its fields are the settings', known when the module runs, not to a type checker
_SessionSettingsBase: Any = create_model("_SessionSettingsBase", __base__=_Request, **_REQUEST_FIELDS)


class SessionSettings(_SessionSettingsBase):
    """A stream's settings (service/registration/settings.py); unset ones take the engine's
    defaults (echoed back when it opens)."""

    skip_stale: bool = Field(
        False,
        description="WebSocket only: when frames queue up behind a solve, solve only the newest good one "
        "(a frame whose support is refused gets its own 422) and say which were skipped (skipped, "
        "skipped_ids; in the error, where the answered frame fails); a skipped frame's support still applies",
    )

    @field_validator("outputs")
    @classmethod
    def _unique(cls, v: list[str]) -> list[str]:
        if len(set(v)) != len(v):
            raise ValueError("outputs repeat a name")
        return v

    @model_validator(mode="after")
    def _trim(self) -> SessionSettings:
        if self.loss == "trimmed" and self.loss_param is not None and self.loss_param >= 1:
            raise ValueError("the trimmed loss's loss_param is a fraction in (0, 1)")
        return self


class SessionCreate(SessionSettings):
    """The first message of a stream, or the body of ``POST /sessions``."""

    model: str = Field(min_length=1, max_length=200, description="a model id from GET /models")


class FrameIn(_Request):
    """One frame: the cloud, optionally a new support, optionally an id to echo."""

    points: Points = Field(description="(m, 3) point cloud in the reference mesh's frame")
    support: NodeIds | None = Field(None, description="a new support for this frame and the ones after")
    frame_id: FrameId | None = Field(None, description="echoed back in the result")


class ForcesIn(_Request):
    nodes: NodeIds = Field(description="(k,) node ids the forces act on")
    values: ForceValues = Field(description="(k, 3) forces, N")

    @model_validator(mode="after")
    def _aligned(self) -> ForcesIn:
        if len(self.nodes) != len(self.values):
            raise ValueError(f"forces: {len(self.nodes)} nodes but {len(self.values)} values")
        return self


class SimulateIn(_Request):
    """The forward problem: displacement under given nodal forces."""

    forces: ForcesIn
    method: ForwardMethod = "network"
    E: Finite | None = Field(None, gt=0, description="Young's modulus, Pa (default: the model's)")


REQUEST_MODELS = (SessionCreate, FrameIn, SimulateIn)


def check_points_limit(obj: Any, max_points: int) -> None:
    """Raise TooManyPoints when a frame body's cloud is over the limit (before validating it)."""
    if not isinstance(obj, dict):
        return
    p = obj.get("points")
    n = p.shape[0] if isinstance(p, np.ndarray) and p.ndim else len(p) if isinstance(p, list) else 0
    if n > max_points:
        raise TooManyPoints(f"{n} points is over this server's limit of {max_points} per frame")


def error_list(exc: ValidationError, prefix: tuple = ("body",)) -> list[dict]:
    """A validation error as FastAPI's 422 ``detail`` list (loc, msg, type), JSON-safe."""
    out = []
    for e in exc.errors(include_url=False, include_context=False, include_input=False):
        out.append({"loc": [*prefix, *e["loc"]], "msg": e["msg"], "type": e["type"]})
    return out


def error_text(errors: list[dict]) -> str:
    """The same errors as one line (WebSocket error messages)."""
    return "; ".join(f"{'.'.join(str(p) for p in e['loc'] if p != 'body') or 'body'}: {e['msg']}" for e in errors)


# -- replies -------------------------------------------------------------------------------------

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Tri = Annotated[list[int], Field(min_length=3, max_length=3)]


class _Reply(BaseModel):
    model_config = ConfigDict(extra="allow")


class Limits(_Reply):
    """Every limit of service/config.py's LIMITS (all listed; these three at least)."""

    max_points: int
    max_sessions: int
    session_ttl_s: float


class SessionCount(_Reply):
    open: int
    http: int
    stream: int


class Health(_Reply):
    status: Literal["ok", "degraded"] = Field(
        description="degraded (HTTP 503): no model loaded, or the solve queue is full"
    )
    reasons: list[str] = Field([], description="why it is degraded")
    models: int
    device: str
    version: str
    limits: Limits
    instance: str = Field(description="this server process (sessions live in the process that made them)")
    sessions: SessionCount
    solver_threads: int
    skipped_models: dict[str, str] = Field(description="store entries that failed to load, and why")


class Material(_Reply):
    law: str
    E: float
    nu: float


class ModelSummary(_Reply):
    id: str
    n_nodes: int
    n_tets: int
    n_surface_nodes: int
    material: Material
    methods: list[ForwardMethod]
    training: dict[str, Any]
    network: dict[str, Any] = {}
    mesh_renumbered: bool = False


class MeshOut(_Reply):
    nodes: list[Vec3]
    tets: list[Annotated[list[int], Field(min_length=4, max_length=4)]]
    surface_faces: list[Tri] = Field(description="outward-oriented boundary triangles")
    surface_nodes: list[int]
    fixed_nodes: list[int]
    region_nodes: list[int] = Field(description="the nodes the network accepts forces on")


class SimulateOut(_Reply):
    displacement: list[Vec3]
    net_force: Vec3
    method: ForwardMethod
    converged: bool
    status: str
    iterations: int
    residual: float | None = None
    error_estimate: float | None = None  # m, the network's: null where infinite (the FEM has residual)
    timing_ms: dict[str, float]


_REPLY_TYPES = {NodeList: list[int], FaceList: list[Tri], Outputs: list[OutputName]}

_REPLY_FIELDS: dict[str, Any] = {f.name: (_reply_field(f, _HINTS[f.name]), ...) for f in SETTINGS}
_SessionConfigBase: Any = create_model("_SessionConfigBase", __base__=_Reply, **_REPLY_FIELDS)


class SessionConfigOut(_SessionConfigBase):
    """The effective settings of a session (every default filled in)."""

    model: str
    skip_stale: bool


class SessionOpened(_Reply):
    session: str
    config: SessionConfigOut
    instance: str


class Counters(_Reply):
    frames: int
    converged: int
    failed: int
    seconds: float
    support_size: int


class SessionInfo(_Reply):
    session: str
    kind: Literal["http", "stream"]
    instance: str
    config: SessionConfigOut
    counters: Counters
    created: float = Field(description="Unix time")
    idle_s: float
    expires_in_s: float | None = Field(description="null for a stream: it lives as long as its socket")


class FrameResult(_Reply):
    frame_id: int | str | None
    converged: bool
    status: str = Field(description="converged, max_iter, time_limit, line_search, forward_failed, ...")
    message: str = ""
    objective: float | None
    distance_rms: float | None
    iterations: int
    evaluations: int
    net_force: Vec3
    alpha: float | None = Field(None, description="the regularisation weight the frame ran with")
    error_estimate: float | None = Field(
        None,
        description="estimated mean nodal error of the displacement, m, without ground truth: the "
        "forward model's residual error plus the misfit the declared noise does not explain (null: none could be made)",
    )
    method_used: ForwardMethod | None = Field(None, description="the forward model that produced this frame")
    displacement: list[Vec3] | None = None
    surface_displacement: list[Vec3] | None = Field(None, description="in the order of the mesh's surface_nodes")
    forces: list[Vec3] | None = Field(None, description="(k, 3) aligned with `support`")
    stress: list[float] | None = Field(None, description="von Mises per tet, Pa")
    support: list[int] | None = Field(None, description="the node ids `forces` are aligned with")
    skipped: int | None = Field(None, description="skip_stale streams: frames skipped before this one")
    skipped_ids: list[int | str | None] | None = None
    timing_ms: dict[str, float] = Field(
        description="engine: total, check, forward, distance, gradient, optimizer, outputs; "
        "server: decode, queue, solve, server, encode"
    )


class ErrorOut(_Reply):
    detail: str | list[dict[str, Any]]


class StreamErrorBody(_Reply):
    code: int
    detail: str
    frame_id: int | str | None = None


class StreamError(_Reply):
    """What a WebSocket stream sends for a frame it cannot take (the stream stays open)."""

    error: StreamErrorBody

"""A session's bodies: its settings (built from service/registration/settings.py), its opening,
its frames and their results, its counters, and a stream's errors."""

from __future__ import annotations

import dataclasses
import types
from typing import Any, Literal, Union, get_args, get_origin, get_type_hints

from pydantic import Field, create_model, field_validator, model_validator

from ...registration.settings import SETTINGS, FaceList, ForwardMethod, NodeList, OutputName, Outputs, SessionConfig
from .arrays import Finite, FrameId, NodeIds, Points, Tri, Triangles, Vec3
from .common import _Reply, _Request


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


class StreamErrorBody(_Reply):
    code: int
    detail: str
    frame_id: int | str | None = None


class StreamError(_Reply):
    """What a WebSocket stream sends for a frame it cannot take (the stream stays open)."""

    error: StreamErrorBody

"""What routes need, as ``Annotated`` dependencies: settings, the loaded models, the session
registry, the solve pool, the reply's encoding and decoded, validated bodies.

Bodies are read here rather than by FastAPI's JSON parsing so that JSON and MessagePack (with
packed arrays) go through one strict decoder; each body dependency returns a :class:`Body`
with the validated model and how long decoding took (reported in the frame's ``timing_ms``).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Annotated, Generic, TypeVar

from fastapi import Depends, Request, Response
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel
from starlette.requests import HTTPConnection

from ..config import Settings, get_settings
from ..store import Entry
from . import codec, errors
from .errors import ApiError
from .schemas import FrameIn, SessionCreate, SimulateIn, check_points_limit
from .sessions import Held, SessionRegistry
from .work import SolvePool, not_found_model

M = TypeVar("M", bound=BaseModel)
_THREAD_DECODE = 256 << 10  # bodies larger than this are decoded off the event loop


@dataclasses.dataclass
class Body(Generic[M]):
    value: M
    decode_ms: float
    t_received: float


# Every dependency is ``async def``: FastAPI runs a plain ``def`` dependency in its thread pool,
# a thread hop per dependency per request for what is an attribute lookup.


async def settings() -> Settings:
    """The settings (create_app overrides this with the app's own)."""
    return get_settings()


async def models(conn: HTTPConnection) -> dict[str, Entry]:
    return conn.app.state.models


async def registry(conn: HTTPConnection) -> SessionRegistry:
    return conn.app.state.registry


async def pool(conn: HTTPConnection) -> SolvePool:
    return conn.app.state.pool


async def reply_kind(request: Request) -> str:
    """The reply's encoding: Accept, else the request's Content-Type, else JSON."""
    return errors.reply_kind(request)


SettingsDep = Annotated[Settings, Depends(settings)]
ModelsDep = Annotated[dict[str, Entry], Depends(models)]
RegistryDep = Annotated[SessionRegistry, Depends(registry)]
PoolDep = Annotated[SolvePool, Depends(pool)]
ReplyKind = Annotated[str, Depends(reply_kind)]


async def entry(model: str, models: ModelsDep) -> Entry:
    found = models.get(model)
    if found is None:
        raise not_found_model(model, models)
    return found


async def http_session(session_id: str, registry: RegistryDep) -> Held:
    return registry.get(session_id, kind="http")


EntryDep = Annotated[Entry, Depends(entry)]
HttpSessionDep = Annotated[Held, Depends(http_session)]


async def read_body(request: Request, settings: Settings):
    """The request's body decoded (JSON or MessagePack), size-limited (413)."""
    kind = codec.request_kind(request.headers.get("content-type"))
    limit = settings.max_body_bytes
    length = request.headers.get("content-length")
    if length and length.isdigit() and int(length) > limit:
        raise ApiError(413, f"body of {length} bytes is over this server's limit of {limit}")
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise ApiError(413, f"body over this server's limit of {limit} bytes")
        chunks.append(chunk)
    data = b"".join(chunks)
    if not data:
        raise ApiError(422, [{"loc": ["body"], "msg": "a body is required", "type": "missing"}])
    if len(data) > _THREAD_DECODE:
        return await run_in_threadpool(codec.decode, data, kind, max_bytes=limit)
    return codec.decode(data, kind, max_bytes=limit)


def _validated(cls: type[M], obj) -> M:
    if not isinstance(obj, dict):
        raise ApiError(422, [{"loc": ["body"], "msg": "the body must be a map (a JSON object)", "type": "model_type"}])
    return cls.model_validate(obj)  # ValidationError -> 422 (errors.install)


async def frame_body(request: Request, settings: SettingsDep) -> Body[FrameIn]:
    t0 = time.perf_counter()
    obj = await read_body(request, settings)
    check_points_limit(obj, settings.max_points)  # 413 before the 422s
    frame = _validated(FrameIn, obj)
    return Body(frame, 1e3 * (time.perf_counter() - t0), t0)


async def create_body(request: Request, settings: SettingsDep) -> Body[SessionCreate]:
    t0 = time.perf_counter()
    obj = await read_body(request, settings)
    return Body(_validated(SessionCreate, obj), 1e3 * (time.perf_counter() - t0), t0)


async def simulate_body(request: Request, settings: SettingsDep) -> Body[SimulateIn]:
    t0 = time.perf_counter()
    obj = await read_body(request, settings)
    return Body(_validated(SimulateIn, obj), 1e3 * (time.perf_counter() - t0), t0)


FrameBody = Annotated[Body[FrameIn], Depends(frame_body)]
CreateBody = Annotated[Body[SessionCreate], Depends(create_body)]
SimulateBody = Annotated[Body[SimulateIn], Depends(simulate_body)]


# -- replies -------------------------------------------------------------------------------------

ALT_MSGPACK = {"application/msgpack": {"schema": {"description": "the same map in MessagePack, arrays packed"}}}


def reply(body, kind: str, status: int = 200) -> Response:
    """A reply in the negotiated encoding: ``body`` is a map to encode, or bytes already encoded."""
    data = body if isinstance(body, bytes) else codec.encode(body, kind)
    return Response(data, status_code=status, media_type=codec.MEDIA[kind])


def request_body(model: type[BaseModel]) -> dict:
    """``openapi_extra`` for a route that reads its body itself: the schema, both encodings."""
    ref = {"$ref": f"#/components/schemas/{model.__name__}"}
    return {"requestBody": {"required": True, "content": {"application/json": {"schema": ref},
                                                          "application/msgpack": {"schema": ref}}}}

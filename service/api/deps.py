"""What routes need, as ``Annotated`` dependencies: who is calling (the bearer token's owner),
settings, the loaded models, the session registry, the solve pool, the reply's encoding and
decoded, validated bodies.

Access is checked here and only here: :func:`owner` is the HTTP dependency (every router but
/health's is included with it, and routes that touch a session take its value as ``Owner``),
:func:`authorize_websocket` the helper every WebSocket route calls with its first message
(through :class:`.sockets.Slot`, which also counts the socket). Both go through :func:`check_token`.

Bodies are read here rather than by FastAPI's JSON parsing so that JSON and MessagePack (with
packed arrays) go through one strict decoder; each body dependency returns a :class:`Body`
with the validated model and how long decoding took (reported in the frame's ``timing_ms``).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import hashlib
import hmac
import time
from collections.abc import Callable, Iterator
from typing import Annotated, Generic, TypeVar

from fastapi import Depends, Request, Response, WebSocket
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel
from starlette.requests import ClientDisconnect, HTTPConnection

from ..config import Settings, get_settings
from ..store import Entry
from . import codec, errors
from .errors import ApiError
from .schemas.common import ErrorOut, check_points_limit
from .schemas.models import SimulateIn
from .schemas.sessions import FrameIn, SessionCreate
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


# -- access --------------------------------------------------------------------------------------

_CHALLENGE = {"WWW-Authenticate": 'Bearer realm="elastreg"'}


def fingerprint(token: str) -> str:
    """What a session keeps of the token that opened it: a digest, never the token itself."""
    return hashlib.sha256(token.encode()).hexdigest()[:24]


def check_token(settings: Settings, token: str | None) -> str | None:
    """The owner a request acts as: None on a server without tokens (open), else the fingerprint
    of ``token`` when it is one of the server's; ApiError 401 for a missing or unknown token.

    >>> check_token(Settings(api_tokens="t" * 16), "t" * 16) == fingerprint("t" * 16)
    True
    """
    if not settings.api_tokens:
        return None
    if not token:
        raise ApiError(401, "this server needs a token: send 'Authorization: Bearer <token>'", _CHALLENGE)
    given = token.encode()
    if not any(hmac.compare_digest(given, t.encode()) for t in settings.api_tokens):  # constant time
        raise ApiError(401, "unknown token", _CHALLENGE)
    return fingerprint(token)


def bearer(header: str | None) -> str | None:
    """The token of an ``Authorization: Bearer <token>`` header (None when there is no header)."""
    if header is None:
        return None
    scheme, _, value = header.strip().partition(" ")
    if scheme.lower() != "bearer" or not value.strip():
        raise ApiError(401, "the Authorization header must be 'Bearer <token>'", _CHALLENGE)
    return value.strip()


async def owner(conn: HTTPConnection, settings: SettingsDep) -> str | None:
    """The HTTP dependency: who is calling (see :func:`check_token`); 401 otherwise."""
    return check_token(settings, bearer(conn.headers.get("authorization")))


Owner = Annotated[str | None, Depends(owner)]


@dataclasses.dataclass(frozen=True)
class HandshakeToken:
    """A WebSocket handshake's ``Authorization`` header, checked once (:func:`handshake_token`,
    at admission): the owner it acts as, or the ApiError that refuses it."""

    owner: str | None = None
    error: ApiError | None = None

    def result(self) -> str | None:
        if self.error is not None:
            raise self.error
        return self.owner


def handshake_token(websocket: WebSocket) -> HandshakeToken | None:
    """The verdict on the handshake's ``Authorization`` header (None when it sent none): the one
    compare of its token, whose result the socket keeps (:class:`.sockets.Slot`)."""
    header = websocket.headers.get("authorization")
    if header is None:
        return None
    try:
        return HandshakeToken(owner=check_token(websocket.app.state.settings, bearer(header)))
    except ApiError as err:
        return HandshakeToken(error=err)


def authorize_websocket(websocket: WebSocket, handshake: HandshakeToken | None, first_message=None) -> str | None:
    """The owner a WebSocket acts as, for every WebSocket route: its handshake's ``Authorization``
    header when it sent one (browsers cannot; ``handshake``, checked at admission), else the
    ``token`` field of its first message (a map; the field is removed from it, so the rest
    validates as the route's own body). Raises ApiError 401 without a valid token on a server
    that has tokens: the route sends that as its error and closes the socket with 1008.

    A route without a first message (one that only sends) passes ``None``: the header is then
    the only way in."""
    token = None
    if isinstance(first_message, dict):
        token = first_message.pop("token", None)
        if token is not None and not isinstance(token, str):
            raise ApiError(401, "the first message's token must be a string")
    if handshake is not None:
        return handshake.result()
    return check_token(websocket.app.state.settings, token)


ModelsDep = Annotated[dict[str, Entry], Depends(models)]
RegistryDep = Annotated[SessionRegistry, Depends(registry)]
PoolDep = Annotated[SolvePool, Depends(pool)]
ReplyKind = Annotated[str, Depends(reply_kind)]


async def entry(model: str, models: ModelsDep) -> Entry:
    found = models.get(model)
    if found is None:
        raise not_found_model(model, models)
    return found


async def http_session(session_id: str, registry: RegistryDep, owner: Owner) -> Held:
    return registry.get(session_id, kind="http", owner=owner)


EntryDep = Annotated[Entry, Depends(entry)]
HttpSessionDep = Annotated[Held, Depends(http_session)]


async def read_body(request: Request, settings: Settings):
    """The request's body decoded (JSON or MessagePack): 415 for another Content-Type, 413 over
    the byte limit (counted as it arrives) or the array-element limit, 408 when it takes longer
    than ``body_timeout_s`` to arrive."""
    kind = codec.request_kind(request.headers.get("content-type"))
    limit = settings.max_body_bytes
    length = request.headers.get("content-length")
    if length and length.isdigit() and int(length) > limit:
        raise ApiError(413, f"body of {length} bytes is over this server's limit of {limit}")
    chunks, size = [], 0
    try:
        async with asyncio.timeout(settings.body_timeout_s):
            async for chunk in request.stream():
                size += len(chunk)
                if size > limit:
                    raise ApiError(413, f"body over this server's limit of {limit} bytes")
                chunks.append(chunk)
    except TimeoutError:
        raise ApiError(408, f"the body did not arrive within {settings.body_timeout_s:g} s") from None
    except ClientDisconnect:  # nobody to answer: not a server error
        raise ApiError(400, "the client disconnected before its body arrived") from None
    data = b"".join(chunks)
    if not data:
        raise ApiError(422, [{"loc": ["body"], "msg": "a body is required", "type": "missing"}])
    limits = {"max_bytes": limit, "max_elements": settings.max_array_elements}
    if len(data) > _THREAD_DECODE:
        return await run_in_threadpool(codec.decode, data, kind, **limits)
    return codec.decode(data, kind, **limits)


@contextlib.contextmanager
def client_gone(request: Request) -> Iterator[Callable[[], bool]]:
    """Within the block, a callable that says whether the client has disconnected (call it
    after the body is read: it watches the connection's next message)."""
    gone = False

    async def watch() -> None:
        nonlocal gone
        while (await request.receive())["type"] != "http.disconnect":
            pass
        gone = True

    task = asyncio.ensure_future(watch())
    try:
        yield lambda: gone
    finally:
        task.cancel()


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
RETRY_AFTER = {"Retry-After": {"description": "seconds to wait before trying again", "schema": {"type": "integer"}}}


def unavailable(description: str, model: type[BaseModel] = ErrorOut) -> dict:
    """A route's OpenAPI 503: every one says when to retry (Retry-After, in seconds)."""
    return {503: {"model": model, "description": description, "headers": RETRY_AFTER}}


def reply(body, kind: str, status: int = 200) -> Response:
    """A reply in the negotiated encoding: ``body`` is a map to encode, or bytes already encoded."""
    data = body if isinstance(body, bytes) else codec.encode(body, kind)
    return Response(data, status_code=status, media_type=codec.MEDIA[kind])


def request_body(model: type[BaseModel]) -> dict:
    """``openapi_extra`` for a route that reads its body itself: the schema, both encodings."""
    ref = {"$ref": f"#/components/schemas/{model.__name__}"}
    return {
        "requestBody": {
            "required": True,
            "content": {"application/json": {"schema": ref}, "application/msgpack": {"schema": ref}},
        }
    }

"""Errors as replies: one exception type for the API's own refusals, and the handlers that turn
every failure into a body in the request's encoding.

    401 no token, or an unknown one, on a server with tokens (WWW-Authenticate: Bearer)
    403 a cross-origin request from an origin not allowed
    404 unknown model or session, or another token's session (the text explains session affinity)
    408 a body that did not arrive within body_timeout_s
    409 a stream's session addressed over HTTP
    413 a body, a point cloud or a body's array elements over the limits
    415 a Content-Type that is neither JSON nor MessagePack
    422 a body that does not decode or validate, or that the engine refuses (ValueError)
    503 the process is at its session limit, its solves are saturated, or it is shutting down;
        always with Retry-After (a stream's error carries it as ``retry_after``)
    500 our bug: logged with its traceback, the reply names only the exception type
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import Response
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException

from . import codec
from .pool import Dropped, Overloaded
from .schemas.common import TooManyPoints, error_list
from .sessions import RegistryFull, SessionNotFound, WrongKind

log = logging.getLogger(__name__)


class ApiError(Exception):
    """A refusal with its HTTP status; ``detail`` is a string or FastAPI's 422 list."""

    def __init__(self, status: int, detail, headers: dict[str, str] | None = None) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.headers = headers

    @property
    def retry_after(self) -> int | None:
        """The seconds of its Retry-After header (a 503's), else None."""
        value = (self.headers or {}).get("Retry-After")
        return int(value) if value is not None else None

    @property
    def text(self) -> str:
        if isinstance(self.detail, list):
            from .schemas.common import error_text

            return error_text(self.detail)
        return str(self.detail)


def unavailable(detail: str, retry_after: int) -> ApiError:
    """A 503 that says when to retry: ``Retry-After`` over HTTP, ``retry_after`` on a stream."""
    return ApiError(503, detail, {"Retry-After": str(retry_after)})


def unprocessable(msg: str, *loc: str | int, type_: str = "value_error") -> ApiError:
    """A 422 in FastAPI's shape, for refusals found after schema validation (the engine's)."""
    return ApiError(422, [{"loc": ["body", *loc], "msg": msg, "type": type_}])


def as_api_error(exc: BaseException) -> ApiError | None:
    """The API error a known exception stands for (None for anything else: a bug)."""
    if isinstance(exc, ApiError):
        return exc
    if isinstance(exc, ValidationError):
        return ApiError(422, error_list(exc))
    if isinstance(exc, codec.TooLarge):
        return ApiError(413, str(exc))
    if isinstance(exc, codec.DecodeError):
        return unprocessable(str(exc), type_="decode_error")
    if isinstance(exc, TooManyPoints):
        return ApiError(413, str(exc))
    if isinstance(exc, codec.UnsupportedMedia):
        return ApiError(415, str(exc))
    if isinstance(exc, SessionNotFound):
        return ApiError(404, str(exc))
    if isinstance(exc, WrongKind):
        return ApiError(409, str(exc))
    if isinstance(exc, RegistryFull):
        return unavailable(str(exc), exc.retry_after)
    if isinstance(exc, Dropped):
        return ApiError(404, str(exc))
    if isinstance(exc, Overloaded):
        return unavailable(str(exc), exc.retry_after)
    return None


def reply_kind(request: Request) -> str:
    return codec.response_kind(request.headers.get("accept"), request.headers.get("content-type"))


def error_response(request: Request, status: int, detail, headers: dict | None = None) -> Response:
    kind = reply_kind(request)
    body = codec.encode({"detail": detail}, kind)
    return Response(body, status_code=status, media_type=codec.MEDIA[kind], headers=headers)


def install(app: FastAPI) -> None:
    """Register the handlers: every error body in the request's encoding."""

    async def api_error(request: Request, exc: Exception) -> Response:
        err = as_api_error(exc)
        return error_response(request, err.status, err.detail, err.headers)

    async def validation(request: Request, exc: RequestValidationError) -> Response:
        detail = [
            {"loc": list(e.get("loc", ())), "msg": str(e.get("msg", "")), "type": str(e.get("type", ""))}
            for e in exc.errors()
        ]
        return error_response(request, 422, detail)

    async def http_error(request: Request, exc: StarletteHTTPException) -> Response:
        return error_response(request, exc.status_code, exc.detail, getattr(exc, "headers", None))

    async def bug(request: Request, exc: Exception) -> Response:
        log.error("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
        return error_response(request, 500, f"internal error ({type(exc).__name__}); it has been logged")

    for cls in (
        ApiError,
        ValidationError,
        codec.DecodeError,
        TooManyPoints,
        codec.UnsupportedMedia,
        SessionNotFound,
        WrongKind,
        RegistryFull,
        Overloaded,
        Dropped,
    ):
        app.add_exception_handler(cls, api_error)
    app.add_exception_handler(RequestValidationError, validation)
    app.add_exception_handler(StarletteHTTPException, http_error)
    app.add_exception_handler(Exception, bug)

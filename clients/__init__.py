"""Clients of the elastreg API: :mod:`.client` (sync and async, HTTP and WebSocket; its
WebSocket handles in :mod:`.sockets`, over :mod:`.errors`, :mod:`.encoding` and :mod:`.bodies`),
the client side of ``elastreg demo`` (:mod:`.demo`) and a local load test (:mod:`.loadtest`).
Nothing here imports the service: a client needs only this package."""

from .client import (
    ApiError,
    AsyncClient,
    AsyncSessionHandle,
    AsyncStream,
    AsyncWatch,
    Client,
    SessionHandle,
    Stream,
    StreamError,
    Watch,
)

__all__ = [
    "ApiError",
    "AsyncClient",
    "AsyncSessionHandle",
    "AsyncStream",
    "AsyncWatch",
    "Client",
    "SessionHandle",
    "Stream",
    "StreamError",
    "Watch",
]

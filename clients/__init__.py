"""Clients of the elastreg API: :mod:`.client` (sync and async, HTTP and WebSocket), the demo
(:mod:`.demo`, ``elastreg demo``) and a local load test (:mod:`.loadtest`)."""

from .client import (
    ApiError,
    AsyncClient,
    AsyncSessionHandle,
    AsyncStream,
    Client,
    SessionHandle,
    Stream,
    StreamError,
)

__all__ = [
    "ApiError",
    "AsyncClient",
    "AsyncSessionHandle",
    "AsyncStream",
    "Client",
    "SessionHandle",
    "Stream",
    "StreamError",
]

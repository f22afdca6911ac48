"""Browser safety at the door, as ASGI middleware (API.md, "Access", "Browsers").

A web page open in any browser on the theatre's network can send requests to the service: a
``text/plain`` POST or a WebSocket handshake needs no CORS preflight, and the browser sends it
with the page's ``Origin``. :class:`OriginGuard` refuses (403) every HTTP request and WebSocket
handshake whose ``Origin`` is neither the service's own nor listed in ``allowed_origins``;
Starlette's ``CORSMiddleware`` (inside it) answers the preflights of the listed ones. The 415
for other content types is the body reader's (:func:`.deps.read_body`).

A server without tokens is open to whoever reaches it, so it binds loopback only; a page could
still reach it through DNS rebinding (a name of the page's own that resolves to 127.0.0.1 makes
the request same-origin). Such a server therefore answers loopback host names only.
"""

from __future__ import annotations

import ipaddress
import logging
from collections.abc import Collection

from starlette.datastructures import Headers
from starlette.responses import Response
from starlette.types import ASGIApp, Receive, Scope, Send

from . import codec

log = logging.getLogger(__name__)

_SCHEME = {"http": "http", "https": "https", "ws": "http", "wss": "https"}
_DEFAULT_PORT = {"http": "80", "https": "443"}


def is_loopback(host: str) -> bool:
    """Whether a host name or address is this machine's loopback (``localhost``, 127/8, ::1).

    >>> [is_loopback(h) for h in ("localhost", "127.0.0.1", "::1", "0.0.0.0", "10.0.0.5", "example.org")]
    [True, True, True, False, False, False]
    """
    host = host.strip("[]").lower()
    if host == "localhost" or host.endswith(".localhost"):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def host_name(host_header: str) -> str:
    """The name of a Host header, without its port (``[::1]:8000`` -> ``::1``)."""
    if host_header.startswith("["):
        return host_header[1 : host_header.find("]")] if "]" in host_header else host_header
    return host_header.rsplit(":", 1)[0] if host_header.count(":") == 1 else host_header


def _origin_of(scheme: str, host_header: str) -> str:
    """The origin a request for ``host_header`` over ``scheme`` belongs to (default port dropped)."""
    port = _DEFAULT_PORT[scheme]
    host = host_header.lower()
    if host.endswith(":" + port) and not host.endswith("]"):
        host = host[: -len(port) - 1]
    return f"{scheme}://{host}"


class OriginGuard:
    """403 for a cross-origin request or handshake from an origin not allowed; on a server
    without tokens (``loopback_only``), 403 for a Host that is not a loopback name."""

    def __init__(self, app: ASGIApp, *, allowed_origins: Collection[str] = (), loopback_only: bool = False) -> None:
        self.app = app
        self.allowed = frozenset(o.rstrip("/").lower() for o in allowed_origins)
        self.loopback_only = loopback_only

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        headers = Headers(scope=scope)
        host = headers.get("host", "")
        if self.loopback_only and not is_loopback(host_name(host)):
            return await self._refuse(
                scope,
                receive,
                send,
                f"this server has no tokens and answers loopback names only (not {host!r}): "
                "start it with tokens (ELASTREG_API_TOKENS) to serve a network",
            )
        origin = headers.get("origin")
        if origin is not None and not self.allows(origin, scope, host):
            return await self._refuse(
                scope,
                receive,
                send,
                f"cross-origin request from {origin!r} refused: that origin is not in ELASTREG_ALLOWED_ORIGINS",
            )
        return await self.app(scope, receive, send)

    def allows(self, origin: str, scope: Scope, host: str) -> bool:
        o = origin.rstrip("/").lower()
        return o in self.allowed or o == _origin_of(_SCHEME.get(scope.get("scheme", "http"), "http"), host)

    async def _refuse(self, scope: Scope, receive: Receive, send: Send, detail: str) -> None:
        log.info("refused %s %s: %s", scope["type"], scope.get("path"), detail)
        response = Response(codec.encode({"detail": detail}, codec.JSON), 403, media_type=codec.MEDIA[codec.JSON])
        if scope["type"] == "http":
            return await response(scope, receive, send)
        await receive()  # websocket.connect
        if "websocket.http.response" in scope.get("extensions", {}):
            return await response(scope, receive, send)  # Starlette sends it as a denial response
        await send({"type": "websocket.close", "code": 1008})  # the server answers the handshake 403

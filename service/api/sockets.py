"""WebSocket admission (API.md, "Access"): every WebSocket route runs inside a
:func:`websocket_slot`, and takes its owner from :meth:`Slot.authorize`.

An open socket counts against ``max_sockets``. On a server with tokens only a socket whose
handshake carried a valid token counts there from its handshake: one without (a browser, which
sends its token in its first message, or a peer with no token at all) counts against the
smaller ``max_tokenless_sockets`` until its first message's token is found, and moves to
``max_sockets`` then. Peers without a token, however many, so hold at most
``max_tokenless_sockets`` sockets (each for ``first_message_timeout_s`` at most) and never the
slots of clients with one. A handshake over either cap is answered 503 with Retry-After; a
first message's token that finds ``max_sockets`` full is a 503 error and a close (1013). A
handshake's token is compared once, at admission: the slot keeps the verdict for the route.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import AsyncIterator

from fastapi import Response, WebSocket

from . import codec
from .deps import HandshakeToken, authorize_websocket, handshake_token
from .errors import unavailable


@dataclasses.dataclass(eq=False)
class Slot:
    """A socket's place: ``tokenless`` while it counts against ``max_tokenless_sockets``."""

    websocket: WebSocket
    tokenless: bool
    handshake: HandshakeToken | None  # its Authorization header's verdict, from admission's one check

    def authorize(self, first_message=None) -> str | None:
        """The owner the socket acts as (:func:`~.deps.authorize_websocket`: ApiError 401 without a
        valid token); a tokenless socket then takes a ``max_sockets`` slot, ApiError 503 when none
        is free."""
        owner = authorize_websocket(self.websocket, self.handshake, first_message)
        if self.tokenless:
            state = self.websocket.app.state
            settings = state.settings
            if state.sockets >= settings.max_sockets:
                raise unavailable(_full(settings.max_sockets), settings.retry_after_s)
            state.tokenless_sockets -= 1
            state.sockets += 1
            self.tokenless = False
        return owner


def _full(cap: int) -> str:
    return f"this server has its maximum of {cap} open WebSockets"


async def deny_websocket(websocket: WebSocket, status: int, detail: str, headers: dict | None = None) -> None:
    """Refuse a WebSocket handshake with an HTTP status (the Denial Response extension, where the
    server has it; else a close before accept, which clients see as a 403)."""
    if "websocket.http.response" in websocket.scope.get("extensions", {}):
        body = codec.encode({"detail": detail}, codec.JSON)
        await websocket.send_denial_response(Response(body, status, headers, media_type=codec.MEDIA[codec.JSON]))
    else:
        await websocket.close(1013 if status == 503 else 1008)


@contextlib.asynccontextmanager
async def websocket_slot(websocket: WebSocket) -> AsyncIterator[Slot | None]:
    """The socket's :class:`Slot` while the block runs; at its cap its handshake is answered 503
    (Retry-After) and the block gets None."""
    state = websocket.app.state
    settings = state.settings
    handshake = handshake_token(websocket)
    tokenless = bool(settings.api_tokens) and (handshake is None or handshake.error is not None)
    if tokenless and state.tokenless_sockets >= settings.max_tokenless_sockets:
        detail = (
            f"this server has its maximum of {settings.max_tokenless_sockets} WebSockets waiting for a token: "
            "send 'Authorization: Bearer <token>' in the handshake, or retry later"
        )
    elif not tokenless and state.sockets >= settings.max_sockets:
        detail = _full(settings.max_sockets)
    else:
        detail = None
    if detail is not None:
        await deny_websocket(websocket, 503, detail, {"Retry-After": str(settings.retry_after_s)})
        yield None
        return
    slot = Slot(websocket, tokenless, handshake)
    if tokenless:
        state.tokenless_sockets += 1
    else:
        state.sockets += 1
    try:
        yield slot
    finally:
        if slot.tokenless:  # it may have moved to max_sockets meanwhile (Slot.authorize)
            state.tokenless_sockets -= 1
        else:
            state.sockets -= 1

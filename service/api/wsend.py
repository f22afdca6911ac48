"""A WebSocket message sent under a deadline of progress (:mod:`service.sendwait`): a stream's
or watcher's client that keeps taking a large message over a slow link is kept, one that takes
nothing for ``send_timeout_s`` (or less than ``send_min_bytes_per_s``) is closed.

Starlette gives a route no transport. uvicorn runs the app with a ``send`` that is a bound
method of the connection's protocol object (websockets-sansio, websockets or wsproto), which
holds ``.transport``; :class:`KeepTransport`, the outermost middleware, keeps it in the scope
before anything of the app wraps ``send`` (and finds it behind uvicorn's own wrapper, its
message logger at log level trace). uvicorn's send returns once the message is in the transport's
buffer (after waiting for that buffer to fall below its low-water mark, or, with the legacy
websockets protocol, to drain), so a send waits for the messages before it: that wait is what
the deadline bounds.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable
from typing import Any

from fastapi import WebSocket
from starlette.types import ASGIApp, Receive, Scope, Send
from starlette.websockets import WebSocketState

from ..config import Settings
from ..sendwait import Stalled, drop, progressing

log = logging.getLogger(__name__)

#: the scope key under which KeepTransport leaves a WebSocket's transport
TRANSPORT = "elastreg.transport"
#: wrappers of the server's send looked through for its transport (uvicorn's trace logger is one)
_WRAPPERS = 4


class KeepTransport:
    """Keeps a WebSocket connection's transport in its scope (TRANSPORT), where the server's
    ``send`` is a method of an object that has one (uvicorn's protocols), or a function that
    wraps such a method (:func:`_inner`); otherwise none, which it logs once."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app
        self.told = False  # that no transport was found: said once, not per connection

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "websocket":
            transport = _transport(send)
            if transport is not None:
                scope[TRANSPORT] = transport
            elif not self.told:
                self.told = True
                log.warning(
                    "WebSocket sends have no transport to watch (the server's send is %r): the deadline "
                    "of progress is off, a send or close must end within send_timeout_s whole, and a "
                    "client that stops reading is let go without a reset",
                    send,
                )
        await self.app(scope, receive, send)


def _transport(send: Any) -> Any:
    """The transport behind ``send``: its object's, through the wrappers :func:`_inner` sees."""
    for _ in range(_WRAPPERS + 1):
        transport = getattr(getattr(send, "__self__", None), "transport", None)
        if callable(getattr(transport, "get_write_buffer_size", None)):
            return transport
        send = _inner(send)
        if send is None:
            return None
    return None


def _inner(send: Any) -> Any:
    """The ``send`` a wrapper function forwards to: the variable of that name in its closure,
    as uvicorn's MessageLoggerMiddleware (log level trace) holds the protocol's send; else None."""
    code, cells = getattr(send, "__code__", None), getattr(send, "__closure__", None)
    if code is None or not cells or "send" not in code.co_freevars:
        return None
    try:
        return cells[code.co_freevars.index("send")].cell_contents
    except ValueError:  # a cell not yet filled: no send to follow
        return None


async def send_message(ws: WebSocket, body: bytes, binary: bool, settings: Settings) -> None:
    """Send ``body`` (as text unless ``binary``); :class:`Stalled` when the client takes none of
    it, or of what was sent before, for ``send_timeout_s``, or takes it more slowly than
    ``send_min_bytes_per_s``: its connection is then reset (:func:`~service.sendwait.drop`).
    Without a transport (another server, Starlette's test client, a wrapper of ``send``
    outside ours) the whole send must end within ``send_timeout_s``, as before this module:
    the only measure there is."""
    await _waited(ws, ws.send_bytes(body) if binary else ws.send_text(body.decode()), len(body), settings)


async def close(ws: WebSocket, code: int, reason: str, settings: Settings) -> None:
    """Close the socket (``reason`` cut to what a close frame holds), under the deadline of a
    send: a close frame waits behind the bytes a client has not taken, so one that stopped
    reading would hold the handler, its socket slot and its session for ever. Past the
    deadline the connection is reset where its transport is known; elsewhere the handler
    goes on and returns (the server closes the socket once its bytes drain)."""
    if ws.client_state != WebSocketState.CONNECTED:
        return
    try:
        await _waited(ws, ws.close(code, reason.encode()[:120].decode(errors="ignore")), 0, settings)
    except Stalled as exc:
        log.info("a WebSocket's client took no close frame (%s): left behind", exc)
    except Exception:  # the client went away meanwhile
        pass


async def _waited(ws: WebSocket, aw: Awaitable[None], size: int, settings: Settings) -> None:
    """``aw`` (a send of ``size`` bytes on ``ws``) under the deadline of progress; with no
    transport in the scope, under ``send_timeout_s`` whole."""
    transport = ws.scope.get(TRANSPORT)
    if transport is None:
        try:
            async with asyncio.timeout(settings.send_timeout_s):
                await aw
        except TimeoutError:
            raise Stalled(f"took no message for {settings.send_timeout_s:g} s") from None
        return
    try:
        await progressing(
            aw, transport, timeout=settings.send_timeout_s, min_rate=settings.send_min_bytes_per_s, size=size
        )
    except Stalled:
        drop(transport)
        raise

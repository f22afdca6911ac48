"""The client's WebSocket handles, sync and async: a stream (``/stream``: frames in, results out)
and a watch (``/sessions/{id}/watch``: a session's frames as it solves them), and how a socket's
messages, refusals and closes become results or :class:`StreamError`. websockets is imported at
a socket's first use."""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import Coroutine, Generator
from typing import Any, Generic, Self, TypeVar

from .bodies import frame_body
from .encoding import decode, encode
from .errors import StreamError, redirected, retry_after, stream_error

_OUT_OF_STEP = (
    "a frame's reply never came (timed out, cancelled or interrupted), so this stream's replies no longer "
    "match its frames: open a new stream"
)


def _pending_error(pending: int) -> StreamError:
    """frame() refused while send()'s replies are still to come: it would return the first of
    them as its own, and every frame() after would be one behind."""
    return StreamError(0, f"{pending} frame(s) sent with send() have replies still to come: recv() them before frame()")


# RFC 6455 7.1.5: the close code of a connection that ended without a close frame received
_ABNORMAL_CLOSURE = 1006

# -- messages ------------------------------------------------------------------------------------


def _message(body: dict, encoding: str) -> bytes | str:
    """A message to send: binary for MessagePack, text for JSON."""
    data = encode(body, encoding)
    return data if encoding == "msgpack" else data.decode()


def _decoded(message):
    """A message received, in whichever encoding it came (binary is MessagePack)."""
    return decode(message, "msgpack" if isinstance(message, (bytes, bytearray)) else "json")


def _is_error(obj) -> bool:
    """Whether a decoded message is a stream's or a watch's error, ``{"error": {...}}``."""
    return isinstance(obj, dict) and set(obj) == {"error"}


def _reply(message, wait_close=None) -> dict:
    """A message as a dict, or its error raised as StreamError; the server closes a socket whose
    first message it refused, and ``wait_close()`` returns that close code."""
    obj = _decoded(message)
    if _is_error(obj):
        raise stream_error(obj["error"], close_code=wait_close() if wait_close is not None else None)
    return obj


# -- refusals and closes -------------------------------------------------------------------------


def refused_status(exc: BaseException | None):
    """The HTTP reply (websockets' InvalidStatus) behind a failed handshake: ``exc`` itself, or
    the redirect that raised it, one websockets would not follow (to http(s)://, say); None if
    no HTTP status came."""
    from websockets.exceptions import InvalidStatus

    while exc is not None and not isinstance(exc, InvalidStatus):
        exc = exc.__cause__ or exc.__context__
    return exc


def handshake_refused(exc) -> StreamError:
    """The StreamError of a handshake the server answered with an HTTP status instead of a
    socket (the socket limit's 503, with its Retry-After; a proxy's redirect)."""
    r = exc.response
    try:
        detail = json.loads(r.body)["detail"]
    except Exception:
        detail = r.body.decode(errors="replace") if r.body else r.reason_phrase
    if 300 <= r.status_code < 400:  # a proxy's redirect, as over HTTP
        detail = redirected(r.headers.get("Location"))
    return StreamError(r.status_code, detail, retry_after=retry_after(r.headers.get("Retry-After")))


def _close_code(ws) -> int | None:
    """The close code of a socket the server is closing (after refusing its first message),
    waiting 2 s at most; None if it stays open."""
    from websockets.exceptions import ConnectionClosed

    try:
        ws.recv(timeout=2.0)
    except ConnectionClosed as exc:
        return _closed_code(exc)
    except Exception:
        pass
    return None


async def _aclose_code(ws) -> int | None:
    """:func:`_close_code` for an asyncio socket."""
    import asyncio

    from websockets.exceptions import ConnectionClosed

    try:
        await asyncio.wait_for(ws.recv(), 2.0)
    except ConnectionClosed as exc:
        return _closed_code(exc)
    except Exception:
        pass
    return None


def _closed_code(exc: Exception) -> int | None:
    rcvd = getattr(exc, "rcvd", None)
    return getattr(rcvd, "code", None)


def _closed_by_server(exc: Exception, what: str = "stream") -> StreamError:
    """The StreamError of a socket found closed (``exc``, websockets' ConnectionClosed): the
    server's close code and reason (1006 where no close frame came; the handle's own close()
    said so where it closed first), status 0."""
    rcvd = getattr(exc, "rcvd", None)
    code = _closed_code(exc) or _ABNORMAL_CLOSURE
    reason = getattr(rcvd, "reason", "") or ""
    if rcvd is None:  # no close frame: the connection dropped (the server gone, a network cut)
        detail = f"the {what}'s connection was lost without a close frame ({exc})"
    elif getattr(exc, "rcvd_then_sent", None) is False:  # our close() came first, the server's echoed it
        detail = reason or f"this {what} was closed by its close() ({rcvd})"
    else:
        detail = reason or f"the server closed the {what} ({rcvd})"
    return StreamError(0, detail, close_code=code, reason=reason)


def _refusal(exc: Exception, late) -> StreamError | None:
    """The server's refusal of a stream found closed while opening (``exc``): its last message
    (``late``, None where none came) where that was an error, with the close's code (the
    handshake's token refused before the config was sent); None where it was not."""
    if late is None:
        return None
    try:
        _reply(late)
    except StreamError as refused:
        refused.close_code = _closed_code(exc)
        return refused
    except Exception:  # not a message this client reads: the close speaks for itself
        return None
    return None


def _raise_if_closed(ws) -> None:
    """Raise a closed socket's close as StreamError: the replies a frame() would wait for will
    never come, so its close, not "recv() them first", is what the caller must hear."""
    from websockets.protocol import State

    if ws.state is State.CLOSED:
        exc = ws.protocol.close_exc
        raise _closed_by_server(exc) from exc


def _unanswered(exc: BaseException, ws) -> None:
    """A socket whose opening went unanswered (timed out, or cancelled while waiting) closes
    without waiting for the closing handshake (websockets' close_timeout, 10 s): a server that
    did not answer its config (frozen, hung) will not answer its close either."""
    if isinstance(exc, (TimeoutError, asyncio.CancelledError)):
        ws.close_timeout = 0


@contextlib.contextmanager
def _closes_as_stream_error(what: str = "stream"):
    """Raise a socket found closed as :class:`StreamError` (websockets' exception its cause)."""
    from websockets.exceptions import ConnectionClosed

    try:
        yield
    except ConnectionClosed as exc:
        raise _closed_by_server(exc, what) from exc


# -- handles -------------------------------------------------------------------------------------


class _Socket:
    """A handle that owns its WebSocket (``ws``): its messages' encoding, how long a reply may
    take, and the session it is on once open."""

    def __init__(self, ws: Any, encoding: str, timeout: float | None) -> None:
        self.ws = ws
        self.encoding = encoding
        self.timeout = timeout
        self.session: str | None = None
        self.config: dict | None = None


class _SyncSocket(_Socket):
    """A sync handle: closed with its socket, or by leaving its block."""

    def close(self) -> None:
        self.ws.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _AsyncSocket(_Socket):
    """:class:`_SyncSocket` for an asyncio WebSocket."""

    async def close(self) -> None:
        await self.ws.close()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()


class Stream(_SyncSocket):
    """A WebSocket stream (sync): ``send`` frames (they may be pipelined), ``recv`` results in
    order, or ``frame`` for both (not while sent frames' results are still to be received). A
    stream error raises :class:`StreamError` (a 503's with ``retry_after``, the seconds to
    wait); the stream goes on. A stream the server closed (idle past its ``session_ttl_s``,
    shutting down, a message over its size limit) raises :class:`StreamError` too, with
    ``close_code`` and ``reason`` set: open a new stream."""

    def __init__(self, ws, encoding: str, config: dict, timeout: float | None = None) -> None:
        super().__init__(ws, encoding, timeout)
        from websockets.exceptions import ConnectionClosed

        self._out_of_step = False
        self._pending = 0  # frames sent with send() whose replies recv() has not taken yet
        try:
            ws.send(_message(config, encoding))
            opened = _reply(ws.recv(timeout=timeout), lambda: _close_code(ws))
            self.session, self.config = opened["session"], opened["config"]
        except ConnectionClosed as exc:
            late = None
            with contextlib.suppress(Exception):  # the server's last words, if any came
                late = ws.recv(timeout=0.5)
            refused = _refusal(exc, late)
            if refused is not None:
                raise refused from None
            raise _closed_by_server(exc) from exc
        except BaseException as exc:
            _unanswered(exc, ws)
            ws.close()
            raise

    def send(self, points, *, support=None, frame_id=None) -> None:
        self._send(_message(frame_body(points, support, frame_id), self.encoding))
        self._pending += 1

    def _send(self, message: bytes | str) -> None:
        with _closes_as_stream_error():
            self.ws.send(message)

    def recv(self, timeout: float | None = None) -> dict:
        try:
            with _closes_as_stream_error():
                message = self.ws.recv(timeout=timeout if timeout is not None else self.timeout)
        except StreamError:  # closed: no reply is to come any more
            self._pending = 0
            raise
        self._pending = max(self._pending - 1, 0)  # a reply or an error, each a frame's
        return _reply(message)

    def frame(self, points, *, support=None, frame_id=None) -> dict:
        """Send one frame and return its result. A call left before its reply came (timed out,
        Ctrl-C) puts the stream out of step (that reply may still come, and would be taken for
        the next frame's): the next frame() raises a StreamError that says so, and a new stream
        is needed. A frame refused before it was sent (bad points) leaves the stream in step.
        While frames sent with send() have replies to come, frame() raises a StreamError (its
        reply would be theirs): recv() them first; the stream goes on. A closed stream raises
        its close instead, at every call."""
        if self._out_of_step:
            raise StreamError(0, _OUT_OF_STEP)
        if self._pending:
            _raise_if_closed(self.ws)
            raise _pending_error(self._pending)
        message = _message(frame_body(points, support, frame_id), self.encoding)
        self._out_of_step = True  # until its reply (or its error) came, whatever ends the call
        try:
            self._send(message)
            reply = self.recv()
        except StreamError:  # the frame's error reply, or the socket closed: nothing pending
            self._out_of_step = False
            raise
        self._out_of_step = False
        return reply


H = TypeVar("H", bound=_AsyncSocket)


class Opening(Generic[H]):
    """An async handle being opened: ``await`` it for the handle, or ``async with`` it for a
    handle closed at the block's end, as the sync client's ``with api.stream(...)`` is."""

    def __init__(self, opening: Coroutine[Any, Any, H]) -> None:
        self._opening = opening
        self._handle: H | None = None

    def __await__(self) -> Generator[Any, None, H]:
        return self._opening.__await__()

    async def __aenter__(self) -> H:
        self._handle = await self._opening
        return self._handle

    async def __aexit__(self, *exc) -> None:
        if self._handle is not None:
            await self._handle.close()


class AsyncStream(_AsyncSocket):
    """A WebSocket stream (asyncio); see :class:`Stream`."""

    def __init__(self, ws, encoding: str, timeout: float | None = None) -> None:
        super().__init__(ws, encoding, timeout)
        self._out_of_step = False
        self._pending = 0  # as Stream's

    async def _open(self, config: dict) -> None:
        import asyncio

        from websockets.exceptions import ConnectionClosed

        try:
            await self.ws.send(_message(config, self.encoding))
            first = await asyncio.wait_for(self.ws.recv(), self.timeout)
            code = await _aclose_code(self.ws) if _is_error(_decoded(first)) else None
            opened = _reply(first, lambda: code)
            self.session, self.config = opened["session"], opened["config"]
        except ConnectionClosed as exc:
            late = None
            with contextlib.suppress(Exception):  # the server's last words, if any came
                late = await asyncio.wait_for(self.ws.recv(), 0.5)
            refused = _refusal(exc, late)
            if refused is not None:
                raise refused from None
            raise _closed_by_server(exc) from exc
        except BaseException as exc:
            _unanswered(exc, self.ws)
            await self.ws.close()
            raise

    async def send(self, points, *, support=None, frame_id=None) -> None:
        await self._send(_message(frame_body(points, support, frame_id), self.encoding))
        self._pending += 1

    async def _send(self, message: bytes | str) -> None:
        with _closes_as_stream_error():
            await self.ws.send(message)

    async def recv(self, timeout: float | None = None) -> dict:
        import asyncio

        wait = timeout if timeout is not None else self.timeout
        try:
            with _closes_as_stream_error():
                message = await asyncio.wait_for(self.ws.recv(), wait)
        except StreamError:  # closed: no reply is to come any more
            self._pending = 0
            raise
        self._pending = max(self._pending - 1, 0)  # a reply or an error, each a frame's
        return _reply(message)

    async def frame(self, points, *, support=None, frame_id=None) -> dict:
        """As :meth:`Stream.frame`: after a call left before its reply came (timed out, or
        cancelled: ``asyncio.wait_for``, ``task.cancel()``), a StreamError (out of step); while
        send()'s replies are to come, a StreamError (recv() them first)."""
        if self._out_of_step:
            raise StreamError(0, _OUT_OF_STEP)
        if self._pending:
            _raise_if_closed(self.ws)
            raise _pending_error(self._pending)
        message = _message(frame_body(points, support, frame_id), self.encoding)
        self._out_of_step = True  # until its reply (or its error) came, whatever ends the call
        try:
            await self._send(message)
            reply = await self.recv()
        except StreamError:  # the frame's error reply, or the socket closed: nothing pending
            self._out_of_step = False
            raise
        self._out_of_step = False
        return reply


def _watching(hello: dict) -> tuple[str, str, dict]:
    """The session, model and config a watch's first message names."""
    return hello["watching"], hello["model"], hello["config"]


class Watch(_SyncSocket):
    """A session's frames as it solves them (sync): ``{"seq", "time", "points", "result"}``.

    Iterate (or call ``recv``) for the next frame, waiting while the session is idle; iteration
    ends when the session does. ``timeout`` bounds the wait for the first message only. Each
    frame is acknowledged when the next is asked for (the caller has handled it), so the server
    sends only a frame or two ahead: a caller slower than the session gets the newest frame next
    and the ones it missed are the gaps in ``seq``. A closed watch raises :class:`StreamError`
    with its ``close_code`` (1000 when the session ended)."""

    def __init__(self, ws, encoding: str, timeout: float | None = None) -> None:
        super().__init__(ws, encoding, timeout)
        self.model: str | None = None
        self._handled: int | None = None  # the seq returned last, acknowledged at the next recv
        from websockets.exceptions import ConnectionClosed

        try:  # the server refuses an unknown session, or another token's, and closes the socket
            self.session, self.model, self.config = _watching(_reply(ws.recv(timeout=timeout), lambda: _close_code(ws)))
            ws.send(_message({"ack": 0}, encoding))  # acknowledging from the first frame on
        except ConnectionClosed as exc:
            ws.close()
            raise _closed_by_server(exc, "watch") from exc
        except BaseException as exc:
            _unanswered(exc, ws)
            ws.close()
            raise

    def recv(self, timeout: float | None = None) -> dict:
        """The next frame, after acknowledging the one returned before; with no ``timeout`` it
        waits as long as the session is idle."""
        from websockets.exceptions import ConnectionClosed

        try:
            if self._handled is not None:
                self.ws.send(_message({"ack": self._handled}, self.encoding))
                self._handled = None
            frame = _reply(self.ws.recv(timeout=timeout))
        except ConnectionClosed as exc:
            raise _closed_by_server(exc, "watch") from exc
        self._handled = frame["seq"]
        return frame

    def __iter__(self):
        while True:
            try:
                yield self.recv()
            except StreamError as exc:
                if exc.close_code == 1000:
                    return
                raise


class AsyncWatch(_AsyncSocket):
    """A session's frames as it solves them (asyncio); see :class:`Watch`. Its ``timeout`` is for
    the first message only: a session may be idle for long."""

    def __init__(self, ws, encoding: str, timeout: float | None = None) -> None:
        super().__init__(ws, encoding, timeout)
        self.model: str | None = None
        self._handled: int | None = None

    async def _open(self) -> None:
        import asyncio

        from websockets.exceptions import ConnectionClosed

        try:
            hello = await asyncio.wait_for(self.ws.recv(), self.timeout)
            code = await _aclose_code(self.ws) if _is_error(_decoded(hello)) else None
            self.session, self.model, self.config = _watching(_reply(hello, lambda: code))
            await self.ws.send(_message({"ack": 0}, self.encoding))
        except ConnectionClosed as exc:
            await self.ws.close()
            raise _closed_by_server(exc, "watch") from exc
        except BaseException as exc:
            _unanswered(exc, self.ws)
            await self.ws.close()
            raise

    async def recv(self, timeout: float | None = None) -> dict:
        """As :meth:`Watch.recv`."""
        import asyncio

        from websockets.exceptions import ConnectionClosed

        try:
            if self._handled is not None:
                await self.ws.send(_message({"ack": self._handled}, self.encoding))
                self._handled = None
            frame = _reply(await asyncio.wait_for(self.ws.recv(), timeout))
        except ConnectionClosed as exc:
            raise _closed_by_server(exc, "watch") from exc
        self._handled = frame["seq"]
        return frame

    def __aiter__(self):
        return self

    async def __anext__(self) -> dict:
        try:
            return await self.recv()
        except StreamError as exc:
            if exc.close_code == 1000:
                raise StopAsyncIteration from None
            raise

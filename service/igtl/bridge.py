"""``elastreg igtl``: an OpenIGTLink server (3D Slicer's OpenIGTLinkIF connects as a client) in
front of the registration API.

The bridge is a client of the HTTP/WebSocket API (:class:`clients.AsyncClient`), never a part
of the engine: each OpenIGTLink client gets one ``/stream`` session, which a viewer can watch
(``/viewer?session=ID``). One client at a time: a second, while the first is connected, is told
so and closed; one that comes as the first leaves (a reconnect) is served at once, while the
first's session closes.

In: ``POLYDATA`` (a model's points, as Slicer sends one) or ``POINT`` named ``cloud`` (the
device name is configurable) is one frame. Out, per frame: ``POLYDATA`` ``registered`` (the
boundary surface's outward triangles at the registered positions) and ``STRING`` ``status``
(JSON). Other messages are ignored and logged; a malformed one is answered with a ``status``
whose JSON holds an ``error``, and the connection goes on.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import os
import socket
import time
from typing import TYPE_CHECKING

import numpy as np

from ..sendwait import Stalled, drop, progressing
from . import protocol as p

if TYPE_CHECKING:
    from clients.client import AsyncStream

log = logging.getLogger(__name__)

#: bodies larger than this are decoded off the event loop (a cloud's cells may be many)
_THREAD_DECODE = 256 << 10
SURFACE = "registered"
STATUS = "status"
#: what a client that vanished without closing (cable pulled, laptop asleep) is probed with:
#: idle seconds, seconds between probes, probes unanswered before the connection is dropped
_KEEPALIVE = (60, 10, 6)
#: seconds a client that connects while another holds the slot waits for that one to leave
#: before it is refused: a client that reconnects closes its old connection first, but the two
#: may arrive together and the close be seen a moment after the new connection
_RECONNECT_GRACE = 1.0
#: close codes of a stream the API ended on purpose (idle past session_ttl_s, going away,
#: restarting): the frame was not taken, so it is sent again over a new session
_CLEAN_CLOSE = (1000, 1001, 1012)


class Surface:
    """The model's boundary: surface node ids and triangles renumbered onto them."""

    def __init__(self, mesh: dict) -> None:
        self.nodes = np.asarray(mesh["nodes"], np.float64)
        self.surface_nodes = np.asarray(mesh["surface_nodes"], np.int64)
        where = np.full(len(self.nodes), -1, np.int64)
        where[self.surface_nodes] = np.arange(self.surface_nodes.size)
        self.triangles = where[np.asarray(mesh["surface_faces"], np.int64)]
        if (self.triangles < 0).any():
            raise ValueError("the model's surface faces use nodes outside its surface nodes")

    def same(self, other: Surface) -> bool:
        return (
            self.nodes.shape == other.nodes.shape
            and np.array_equal(self.nodes, other.nodes)
            and np.array_equal(self.surface_nodes, other.surface_nodes)
            and np.array_equal(self.triangles, other.triangles)
        )

    def positions(self, result: dict) -> np.ndarray:
        """(s, 3) registered positions of the surface nodes."""
        if "surface_displacement" in result:
            u = np.asarray(result["surface_displacement"], np.float64)
        else:
            u = np.asarray(result["displacement"], np.float64)[self.surface_nodes]
        return self.nodes[self.surface_nodes] + u


class Bridge:
    def __init__(
        self,
        api_url: str,
        model: str,
        *,
        device: str = "cloud",
        settings: dict | None = None,
        encoding: str = "msgpack",
        token: str | None = None,
    ) -> None:
        self.api_url = api_url
        self.model = model
        self.device = device
        self.token = token  # for a server with tokens: a header on HTTP, the stream's first message
        self.settings = dict(settings or {})
        outputs = set(self.settings.get("outputs") or ["forces"])
        self.settings["outputs"] = sorted(outputs | {"surface_displacement"})
        self.encoding = encoding
        self.surface: Surface | None = None
        #: the API's limits (its /health), read at prepare(): max_points, max_message_bytes,
        #: body_timeout_s (also how long the rest of a message may take once its header began)
        self.limits: dict = {}
        self._client: _Client | None = None  # the client that holds the one slot
        self.sessions: list[str] = []  # ids of the sessions opened so far (for logs and tests)
        self._ignored: set[tuple[str, str]] = set()  # (type, device) of messages ignored so far
        self.announce = log.info  # what to do with a line a person should see (the CLI prints it)

    async def prepare(self) -> None:
        """Read the API's limits and the model's mesh; BridgeError (one line) when it cannot."""
        from clients.client import ApiError

        async with self._api() as api:
            try:
                try:
                    self.limits = dict((await api.health()).get("limits") or {})
                except ApiError:  # a degraded server (503) still names its limits; the mesh says more
                    self.limits = {}
                self.surface = Surface(await api.mesh(self.model))
            except ApiError as exc:
                raise BridgeError(f"the API at {self.api_url} refused model {self.model!r}: {exc}") from None
            except (OSError, _http_error()) as exc:
                raise BridgeError(
                    f"the API at {self.api_url} cannot be reached ({type(exc).__name__}: {exc})"
                ) from None

    @property
    def busy(self) -> bool:
        """Whether a client holds the slot: connected, and not leaving (see _Client.gone)."""
        return self._client is not None and not self._client.gone()

    async def _left(self) -> None:
        """Until no client holds the slot (its socket looked at every 50 ms: a reader paused on
        a full buffer does not see its peer's close)."""
        while (held := self._client) is not None and not held.gone():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(held.left.wait(), 0.05)

    @property
    def send_timeout(self) -> float:
        """Seconds an answer may wait for the client to take it (the API's send_timeout_s)."""
        return float(self.limits.get("send_timeout_s") or 30.0)

    @property
    def send_min_rate(self) -> float:
        """Bytes a second below which a client taking an answer is as good as stalled (the API's
        send_min_bytes_per_s; its default where an older API lists none)."""
        from ..config import Settings

        return float(self.limits.get("send_min_bytes_per_s") or Settings.model_fields["send_min_bytes_per_s"].default)

    async def _drain(self, writer) -> None:
        """Until the client has taken what was written. The deadline is one of progress
        (service.sendwait): a client that takes nothing for send_timeout, or takes an answer more
        slowly than send_min_rate, is _Stalled (it would hold the only slot while it stays
        connected); one that keeps taking bytes (a large surface over a slow link) is waited for."""
        try:
            await progressing(writer.drain(), writer.transport, timeout=self.send_timeout, min_rate=self.send_min_rate)
        except Stalled as exc:
            drop(writer.transport)  # a status or a FIN would wait behind what it does not take
            raise _Stalled(f"its answer: {exc}") from None

    @property
    def read_timeout(self) -> float:
        """Seconds the rest of a message may take once its first byte came (the API's body_timeout_s)."""
        return float(self.limits.get("body_timeout_s") or 30.0)

    def _api(self):
        from clients import AsyncClient

        api = AsyncClient(self.api_url, encoding=self.encoding)
        if self.token:
            api.http.headers["Authorization"] = f"Bearer {self.token}"
        return api

    # -- one connection --------------------------------------------------------------------------

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        client = _Client(reader, writer)
        if self.busy:  # a reconnecting client's close may be seen a moment after its new connection
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._left(), _RECONNECT_GRACE)
        if self.busy:
            log.warning("refusing %s: a client is already connected", client.peer)
            await self._tell(client, _error_body(503, "this bridge serves one client at a time; one is connected"))
            await _close(writer, self.send_timeout)
            return
        self._client = client
        _keepalive(writer.get_extra_info("socket"))
        log.info("client %s connected", client.peer)
        error: dict | str | None = None  # the last status, when the connection ends on an error
        try:
            await self._serve(client)
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        except _Refused as exc:  # the API refused or could not be reached: the client is told
            log.warning("client %s: %s", client.peer, exc)
            error = _error_body(exc.code, str(exc), exc.retry_after)
        except _Stalled as exc:  # the slot is freed: a stalled or vanished client holds it no longer
            log.warning("client %s: %s; closing it", client.peer, exc)
            error = _error_body(408, str(exc))  # the HTTP API's code for a body that comes too slowly
        except Exception as exc:  # a bug: this client is told and closed, the next is served
            log.exception("client %s: internal error", client.peer)
            error = _error_body(500, f"internal error in the bridge ({type(exc).__name__}); it has been logged")
        finally:
            # the slot is freed before the teardown (the last status, the API stream, the socket
            # can take a while): a client that reconnects at once is served meanwhile, and the
            # teardown closes only what is this client's own
            client.left.set()
            if self._client is client:
                self._client = None
            if error is not None:
                await self._tell(client, error)
            await _close_stream(client.stream)
            await _close(writer, self.send_timeout)
            log.info("client %s disconnected", client.peer)

    async def _tell(self, client: _Client, error) -> None:
        """A last status (an ``error``) before the connection closes, under the send deadline;
        nothing to a client dropped for not taking its answers, or if it cannot go."""
        if client.writer.transport.is_closing():
            return
        with contextlib.suppress(Exception):
            client.writer.write(_status({"error": error}, client.version))
            await self._drain(client.writer)

    async def _open(self, api):
        """A stream for this client, and the model's mesh read again (the API may have restarted
        with the model rebuilt); _Refused (with the API's status, 503 if it is unreachable)."""
        from clients.client import ApiError

        extra = {"token": self.token} if self.token else {}
        try:
            stream = await api.stream(self.model, **self.settings, **extra)
        except ApiError as exc:
            raise _Refused(exc.status or 503, f"the API refused the session: {exc.detail}", exc.retry_after) from None
        except (OSError, TimeoutError, *_ws_errors()) as exc:
            raise _Refused(503, f"the API at {self.api_url} cannot be reached ({type(exc).__name__}: {exc})") from None
        try:
            surface = Surface(await api.mesh(self.model))
        except BaseException as exc:
            with contextlib.suppress(Exception):
                await stream.close()
            if isinstance(exc, ApiError):
                raise _Refused(exc.status or 503, f"the API refused the model's mesh: {exc.detail}") from None
            if isinstance(exc, (OSError, TimeoutError, _http_error())):
                raise _Refused(
                    503, f"the API at {self.api_url} cannot be reached ({type(exc).__name__}: {exc})"
                ) from None
            raise
        if self.surface is not None and not self.surface.same(surface):
            log.warning(
                "model %r: its mesh changed (the API restarted with it rebuilt?); the new one is used", self.model
            )
        self.surface = surface
        self.sessions.append(stream.session)
        from clients.client import viewer_url

        self.announce(f"session {stream.session}: watch it at {viewer_url(self.api_url, stream.session)}")
        return stream

    async def _serve(self, client: _Client) -> None:
        """Frames until the client leaves; its stream is left open on ``client`` (the caller
        closes it once the slot is free)."""
        writer = client.writer
        async with self._api() as api:
            client.stream = await self._open(api)
            frame = 0
            while True:
                msg = await self._read(client)
                if msg is None:
                    continue
                points = await self._cloud(msg, writer)
                if points is None:
                    continue
                too_large = self._too_large(points)
                if too_large is not None:  # answered as the API would, and the session is kept
                    log.warning("frame %d: %s", frame, too_large)
                    await self._frame_error(writer, frame, 413, too_large, msg.version)
                else:
                    await self._frame(api, client, frame, points, msg.version)
                frame += 1

    async def _read(self, client: _Client) -> p.Message | None:
        """The next message; None (answered or logged) when it is malformed or not for us.
        A client may be quiet between messages as long as it likes; once a message began, the
        rest must come within read_timeout (_Stalled past it)."""
        first = await client.reader.readexactly(1)
        try:
            async with asyncio.timeout(self.read_timeout):
                return await self._read_rest(first, client)
        except TimeoutError:
            raise _Stalled(f"no complete message within {self.read_timeout:g} s of its start") from None

    async def _read_rest(self, first: bytes, client: _Client) -> p.Message | None:
        reader, writer = client.reader, client.writer
        raw = first + await reader.readexactly(p.HEADER_SIZE - 1)
        try:
            version, mtype, device, ts, size, crc = p.parse_header(raw)
        except p.ProtocolError as exc:
            size = int.from_bytes(raw[42:50], "big")
            if size > p.MAX_BODY:  # cannot find the next message: the connection is lost
                await self._error(writer, exc, client.version)
                raise ConnectionError(str(exc)) from None
            await reader.readexactly(size)
            await self._error(writer, exc, client.version)
            return None
        client.version = min(version, 2)
        body = await reader.readexactly(size)
        try:
            return p.parse_body(version, mtype, device, ts, body, crc)
        except p.ProtocolError as exc:
            await self._error(writer, exc, version)
            return None

    async def _cloud(self, msg: p.Message, writer) -> np.ndarray | None:
        if msg.device != self.device or msg.type not in ("POLYDATA", "POINT"):
            key = (msg.type, msg.device)  # a warning the first time, then quietly (a sender may repeat it)
            log.log(
                logging.INFO if key in self._ignored else logging.WARNING,
                "ignored a %s message named %r (frames are POLYDATA or POINT named %r)",
                msg.type,
                msg.device,
                self.device,
            )
            self._ignored.add(key)
            return None
        decode = p.decode_polydata if msg.type == "POLYDATA" else p.decode_point
        try:
            if len(msg.content) > _THREAD_DECODE:  # a large body's cells are read off the event loop
                decoded = await asyncio.to_thread(decode, msg.content)
            else:
                decoded = decode(msg.content)
        except p.ProtocolError as exc:
            await self._error(writer, exc, msg.version)
            return None
        points = decoded.points if isinstance(decoded, p.PolyData) else decoded
        # OpenIGTLink carries float32, and the API reads packed float32 ("<f4"): sent as it came
        # in MessagePack (half the bytes of float64); JSON numbers are written from float64
        return np.asarray(points, np.float32 if self.encoding == "msgpack" else np.float64)

    def _too_large(self, points: np.ndarray) -> str | None:
        """Why the API would refuse this cloud for its size (413), or None: told here, so that
        the stream (and its session) lives on (a message over max_message_bytes closes it)."""
        n = len(points)
        max_points = self.limits.get("max_points")
        if max_points and n > max_points:
            return f"{n} points is over this server's limit of {max_points} per frame"  # the API's words
        max_bytes = self.limits.get("max_message_bytes")
        size = points.nbytes + 256  # a packed array and the frame's map around it
        if max_bytes and self.encoding == "msgpack" and size > max_bytes:
            return f"a frame of {n} points ({size} bytes) is over this server's limit of {max_bytes} bytes per message"
        return None

    async def _frame(self, api, client: _Client, frame: int, points: np.ndarray, version: int) -> None:
        """Register one frame and answer it. ``client.stream`` is the stream to use next (None
        when it was lost: the frame is answered with an error and the next opens a new session).
        A stream the API closed cleanly (idle past its session_ttl_s, restarting) before it
        answered is reopened and the frame sent once more: only a second failure is an error."""
        from clients.client import StreamError

        writer = client.writer
        t0 = time.perf_counter()
        r = None
        for attempt in (0, 1):
            if client.stream is None:  # the API went away at an earlier frame, or closed the stream
                try:
                    client.stream = await self._open(api)
                except _Refused as exc:
                    log.warning("%s", exc)
                    await self._frame_error(writer, frame, exc.code, str(exc), version, exc.retry_after)
                    return
            stream = client.stream
            lost: BaseException
            try:
                r = await stream.frame(points, frame_id=frame)
                break
            except StreamError as exc:
                if exc.close_code is None:  # the API's error message, or the stream out of step
                    await self._frame_error(writer, frame, exc.status, str(exc.detail), version, exc.retry_after)
                    if exc.status != 0:  # an error message: the stream goes on
                        return
                    client.stream = None
                    await _close_stream(stream)  # out of step (status 0) ends the stream
                    return
                lost = exc  # the API closed the stream (close_code)
            except (OSError, TimeoutError, *_ws_errors()) as exc:
                lost = exc
            client.stream = None
            await _close_stream(stream)
            code = _clean_close(lost)
            if attempt == 0 and code is not None:
                reason = lost.reason if isinstance(lost, StreamError) else ""
                log.warning(
                    "frame %d: the API closed the stream (%d%s); a new session for it (the warm start is lost)",
                    frame,
                    code,
                    f" {reason}" if reason else "",
                )
                continue
            why = _lost(lost)
            log.warning("frame %d: the API stream was lost (%s)", frame, why)
            await self._frame_error(
                writer, frame, 503, f"the API stream was lost ({why}); the next frame opens a new session", version
            )
            return
        stream = client.stream
        assert r is not None and stream is not None and self.surface is not None
        surface = self.surface.positions(r)
        status = {
            "frame_id": r.get("frame_id"),
            "converged": bool(r["converged"]),
            "status": r["status"],
            "net_force": np.asarray(r["net_force"], float).tolist(),
            "error_estimate": r.get("error_estimate"),
            "timing_ms": {**r.get("timing_ms", {}), "bridge": 1e3 * (time.perf_counter() - t0)},
            "session": stream.session,
        }
        writer.write(
            p.pack(
                "POLYDATA",
                SURFACE,
                p.encode_polydata(surface, self.surface.triangles),
                version=version,
            )
        )
        writer.write(_status(status, version))
        await self._drain(writer)

    async def _frame_error(
        self, writer, frame: int, code: int, detail: str, version: int, retry_after: float | None = None
    ) -> None:
        """A frame's answer when it has no result: its id and the error."""
        writer.write(_status({"frame_id": frame, "error": _error_body(code, detail, retry_after)}, version))
        await self._drain(writer)

    async def _error(self, writer, exc: p.ProtocolError, version: int) -> None:
        """A malformed message's answer: its error in the shape a refused frame's has."""
        log.warning("malformed message: %s", exc)
        writer.write(_status({"error": _error_body(exc.code, str(exc))}, version))
        await self._drain(writer)


def _status(obj: dict, version: int) -> bytes:
    return p.pack(
        "STRING",
        STATUS,
        p.encode_string(json.dumps(_json_safe(obj), allow_nan=False, default=float)),
        version=min(version, 2),
    )


def _error_body(code: int, detail: str, retry_after: float | None = None) -> dict:
    """An error as the API words it: a 503's ``retry_after`` (seconds) passed on when it gave one."""
    body: dict = {"code": code, "detail": detail}
    if retry_after is not None:
        body["retry_after"] = retry_after
    return body


def _json_safe(obj):
    """Non-finite numbers as null (a frame result may hold them: status non_finite)."""
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


class _Client:
    """One OpenIGTLink connection and what is its own: the header version it speaks and its API
    stream. Per connection, not on the Bridge: a client that leaves is torn down while the next
    is served, and its teardown must reach nothing of the next one's."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader = reader
        self.writer = writer
        self.peer = writer.get_extra_info("peername")
        self.version = 1  # its header version (1 until its first message)
        self.stream: AsyncStream | None = None  # its API stream, while one is open
        #: set once it sends nothing more: it closed its side of the connection or lost it (what
        #: it sent before is still read, registered and answered), or its frames are over
        self.left = reader.ended if isinstance(reader, _Reader) else asyncio.Event()
        self._socket = writer.get_extra_info("socket")

    def gone(self) -> bool:
        """Whether it has left (``left``), its socket's TCP state included: past 128 KiB unread
        the reader stops reading, and so never sees the close behind those bytes."""
        if not self.left.is_set() and _peer_closed(self._socket):
            self.left.set()
        return self.left.is_set()


#: Linux's TCP states in which the peer has closed its side or the connection is over
#: (include/net/tcp_states.h: CLOSE, CLOSE_WAIT, LAST_ACK, CLOSING)
_PEER_CLOSED = frozenset((7, 8, 9, 11))


def _peer_closed(sock) -> bool:
    """Whether the socket's peer has closed (or the socket is gone), whatever is still unread;
    False where the system does not tell (no TCP_INFO)."""
    if sock is None or not hasattr(socket, "TCP_INFO"):
        return False
    try:
        state = sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 1)[0]
    except OSError:
        return True
    return state in _PEER_CLOSED


class _Reader(asyncio.StreamReader):
    """A StreamReader whose ``ended`` is set when its peer closes its side or the connection is
    lost, even while bytes it sent before are unread (at_eof() waits for those)."""

    def __init__(self, *, loop: asyncio.AbstractEventLoop) -> None:
        super().__init__(loop=loop)
        self.ended = asyncio.Event()

    def feed_eof(self) -> None:
        self.ended.set()
        super().feed_eof()

    def set_exception(self, exc: Exception) -> None:
        self.ended.set()
        super().set_exception(exc)


class BridgeError(RuntimeError):
    """The bridge cannot start (the API refuses the model or cannot be reached, the port is
    taken): its text is one line that says why."""


class _Stalled(Exception):
    """A client began a message and did not finish it in time, took nothing of its answer for
    send_timeout, or vanished."""


class _Refused(Exception):
    """The API refused a session, or could not be reached: `code` is the status to report."""

    def __init__(self, code: int, text: str, retry_after: float | None = None) -> None:
        super().__init__(text)
        self.code = code
        self.retry_after = retry_after


def _ws_errors() -> tuple[type[BaseException], ...]:
    from websockets.exceptions import WebSocketException

    return (WebSocketException,)


def _http_error() -> type[BaseException]:
    import httpx

    return httpx.TransportError


def _clean_close(exc: BaseException) -> int | None:
    """The close code of a stream the API closed on purpose (see _CLEAN_CLOSE), else None: the
    client raises a closed stream as its StreamError, with the server's ``close_code``."""
    from clients.client import StreamError

    if not isinstance(exc, StreamError) or exc.close_code not in _CLEAN_CLOSE:
        return None
    return exc.close_code


def _lost(exc: BaseException) -> str:
    """How a stream was lost, in a few words: the API's close code and reason, or the error."""
    from clients.client import StreamError

    if isinstance(exc, StreamError) and exc.close_code == 1006:  # no close frame came
        return "the connection to the API dropped, 1006"
    if isinstance(exc, StreamError) and exc.close_code is not None:
        return f"closed by the API, {exc.close_code}{f' {exc.reason}' if exc.reason else ''}"
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


async def _close_stream(stream) -> None:
    with contextlib.suppress(Exception):
        await stream.close()


def _keepalive(sock) -> None:
    """TCP keepalive on an accepted socket: a peer gone without a word is noticed (_KEEPALIVE)."""
    if sock is None:
        return
    with contextlib.suppress(OSError):
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
        for name, value in zip(("TCP_KEEPIDLE", "TCP_KEEPINTVL", "TCP_KEEPCNT"), _KEEPALIVE, strict=True):
            if hasattr(socket, name):  # Linux; elsewhere the system's defaults
                sock.setsockopt(socket.IPPROTO_TCP, getattr(socket, name), value)


async def _close(writer, timeout: float) -> None:
    """Close a client's connection; one that does not take its last bytes within ``timeout`` is
    reset (sendwait.drop): closed plainly, the system would offer them to it for minutes."""
    try:
        writer.close()
        await asyncio.wait_for(writer.wait_closed(), timeout)
    except Exception:
        with contextlib.suppress(Exception):
            drop(writer.transport)


async def serve(bridge: Bridge, host: str, port: int, ready=None) -> None:
    """Serve until cancelled; ``ready`` (a callable) is told the bound port."""
    await bridge.prepare()
    loop = asyncio.get_running_loop()

    def connection() -> asyncio.StreamReaderProtocol:  # asyncio.start_server's, with a _Reader
        return asyncio.StreamReaderProtocol(_Reader(loop=loop), bridge.handle, loop=loop)

    try:
        server = await loop.create_server(connection, host, port)
    except OSError as exc:
        why = os.strerror(exc.errno) if exc.errno else str(exc)  # not asyncio's whole sentence
        raise BridgeError(f"cannot listen on {host}:{port}: {why}") from None
    bound = server.sockets[0].getsockname()[1]
    log.info(
        "OpenIGTLink bridge for model %r on %s:%d (API %s)",
        bridge.model,
        host,
        bound,
        bridge.api_url,
    )
    if ready is not None:
        ready(bound)
    async with server:
        await server.serve_forever()


def run(
    model: str,
    *,
    host: str = "127.0.0.1",
    port: int = 18944,
    server: str | None = None,
    store=None,
    device: str = "cloud",
    settings: dict | None = None,
    token: str | None = None,
) -> int:
    """``elastreg igtl``: the bridge, over ``server`` or an API it starts in this process."""
    from contextlib import ExitStack

    with ExitStack() as stack:
        if server is None:
            from ..api.server import BackgroundServer
            from ..config import Settings, default_store

            api = stack.enter_context(BackgroundServer(Settings(store=store or default_store())))
            server = api.url
        bridge = Bridge(server, model, device=device, settings=settings, token=token)
        bridge.announce = lambda line: print(f"elastreg igtl: {line}", flush=True)

        def ready(bound: int) -> None:
            print(
                f"elastreg igtl: OpenIGTLink on {host}:{bound}, model {model!r}, API {server} "
                f"(frames: POLYDATA or POINT named {device!r})",
                flush=True,
            )

        try:
            asyncio.run(serve(bridge, host, port, ready))
        except KeyboardInterrupt:
            pass
        except BridgeError as exc:  # one line, as `elastreg serve` refuses a bad start
            raise SystemExit(f"error: {exc}") from None
    return 0

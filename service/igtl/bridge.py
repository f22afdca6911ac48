"""``elastreg igtl``: an OpenIGTLink server (3D Slicer's OpenIGTLinkIF connects as a client) in
front of the registration API.

The bridge is a client of the HTTP/WebSocket API (:class:`clients.AsyncClient`), never a part
of the engine: each OpenIGTLink client gets one ``/stream`` session, which a viewer can watch
(``/viewer?session=ID``). One client at a time: a second, while the first is connected, is told
so and closed; one that comes as the first leaves (a reconnect) takes the slot at once, and its
session opens once the first's frame in flight is answered and its session closed (refused with
a 503 if no such teardown ends for the API's frame cap plus ``idle_timeout``: the API is not
answering); one that
comes while the first is silent (a Slicer that crashed or slept and left its connection
half-open) takes the slot once the first has been silent for ``idle_timeout``, if it is still
connected then (a TCP probe that closed evicts no one).

In: ``POLYDATA`` (a model's points, as Slicer sends one) or ``POINT`` named ``cloud`` (the
device name is configurable) is one frame. Out, per frame: ``POLYDATA`` ``registered`` (the
boundary surface's outward triangles at the registered positions) and ``STRING`` ``status``
(JSON). Other messages are ignored and logged; a malformed one is answered with a ``status``
whose JSON holds an ``error``, and the connection goes on.

Here the server and its one slot; :mod:`.connection` one client's reading and answering,
:mod:`.relay` the API side (sessions, frames), :mod:`.answers` the status and error bodies.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import os
import socket
import sys
import time

import numpy as np

from . import protocol as p
from .answers import error_body
from .connection import ClientStalled, Connection, ConnectionReader, Evicted, keepalive
from .lograte import Seen, Throttle
from .relay import ApiRefused, BridgeError, Relay, Surface, close_stream

__all__ = ["Bridge", "BridgeError", "Surface", "run", "serve"]

log = logging.getLogger(__name__)

#: bodies larger than this are decoded off the event loop (a cloud's cells may be many)
_THREAD_DECODE = 256 << 10
#: seconds a client that connects while another holds the slot waits for that one to leave
#: before it is refused: a client that reconnects closes its old connection first, but the two
#: may arrive together and the close be seen a moment after the new connection
_RECONNECT_GRACE = 1.0
#: seconds a client may stay silent (no message sent, none being answered) and keep the slot
#: from a new connection (`elastreg igtl --idle-timeout`): longer than a pause between clouds,
#: shorter than a user who restarted Slicer will wait before giving up; also the margin past the
#: API's frame cap a new connection waits for a previous one's session to close (Bridge.teardown_bound)
IDLE_TIMEOUT = 10.0
#: seconds the connections' teardown may take when the bridge stops (Ctrl-C)
_STOP_GRACE = 5.0


class Bridge(Relay):
    """The OpenIGTLink side: the one client slot, each connection's messages turned into frames
    for the relay (:class:`~.relay.Relay`), and the connection's end, whatever ended it."""

    def __init__(
        self,
        api_url: str,
        model: str,
        *,
        device: str = "cloud",
        settings: dict | None = None,
        encoding: str = "msgpack",
        token: str | None = None,
        idle_timeout: float | None = None,
    ) -> None:
        super().__init__(api_url, model, settings=settings, encoding=encoding, token=token)
        self.device = p.check_device_name(device)  # a longer name no message could carry
        self.idle_timeout = IDLE_TIMEOUT if idle_timeout is None else idle_timeout
        if not 0 < self.idle_timeout < float("inf"):
            raise ValueError(f"idle_timeout must be a positive finite number of seconds, got {idle_timeout!r}")
        self._client: Connection | None = None  # the client that holds the one slot
        #: the clients that took the slot and whose teardown is not over: the next waits for them
        self._tearing: set[Connection] = set()
        self._ignored = Seen()  # (type, device) of messages ignored lately (an LRU: a peer may send any number)
        self._throttle = Throttle(log)  # the lines clients' messages cause, all clients together

    @property
    def busy(self) -> bool:
        """Whether a client holds the slot: connected, and not leaving (see Connection.gone)."""
        return self._client is not None and not self._client.gone()

    async def _left(self) -> None:
        """Until no client holds the slot (its socket looked at every 50 ms: a reader paused on
        a full buffer does not see its peer's close)."""
        while (held := self._client) is not None and not held.gone():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(held.left.wait(), 0.05)

    async def _evict_if_silent(self, newcomer: Connection, arrived: float) -> None:
        """Evict the client holding the slot once it has been silent for idle_timeout, if it was
        silent since before ``arrived`` (the newcomer's time) and stays so. Returns at once, the
        slot kept, if it was not silent then or speaks since (a message begun), and as soon as it
        leaves on its own or the newcomer vanishes (a TCP probe evicts no one); waits at most
        idle_timeout."""
        held = self._client
        while held is not None and not held.gone():
            quiet_since = held.quiet_since
            if quiet_since is None or quiet_since > arrived or newcomer.vanished():
                return
            silent = time.monotonic() - quiet_since
            if silent >= self.idle_timeout:  # the newcomer checked above, in this same loop pass
                log.warning("client %s silent for %.1f s: a new connection takes the slot", held.peer, silent)
                held.evict(
                    f"another client took this bridge's one slot after this one sent nothing for {silent:.1f} s "
                    f"(the bridge's idle timeout is {self.idle_timeout:g} s)"
                )
                return
            with contextlib.suppress(TimeoutError):  # polled: its silence is a clock, not an event
                await asyncio.wait_for(held.left.wait(), min(0.05, self.idle_timeout - silent))

    # -- one connection --------------------------------------------------------------------------

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        client = Connection(
            reader,
            writer,
            send_timeout=self.send_timeout,
            send_min_rate=self.send_min_rate,
            read_timeout=self.read_timeout,
            throttle=self._throttle,
        )
        arrived = time.monotonic()
        if self.busy:  # a reconnecting client's close may be seen a moment after its new connection
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._left(), _RECONNECT_GRACE)
        if self.busy:  # a client that stays silent past the idle bound gives the slot up
            await self._evict_if_silent(client, arrived)
        if client.vanished():  # left while it waited (a TCP probe): no session, nothing to tell
            log.info("client %s left before it was served", client.peer)
            await client.close()
            return
        if self.busy:
            log.warning("refusing %s: a client is already connected", client.peer)
            await client.tell(error_body(503, "this bridge serves one client at a time; one is connected"))
            await client.close()
            return
        self._client = client
        earlier = list(self._tearing)
        self._tearing.add(client)
        keepalive(writer.get_extra_info("socket"))
        log.info("client %s connected", client.peer)
        error: dict | str | None = None  # the last status, when the connection ends on an error
        try:
            if earlier:  # their frames in flight and sessions end first: a client that reconnects
                await self._torn_down(earlier)  # in a loop holds one API session, not one each
            if client.reader.at_eof():  # left while it waited, having sent nothing: no session
                return
            await self._serve(client)
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        except ApiRefused as exc:  # the API refused or could not be reached: the client is told
            log.warning("client %s: %s", client.peer, exc)
            error = error_body(exc.code, str(exc), exc.retry_after)
        except asyncio.CancelledError:  # the bridge stops (Ctrl-C): the client is told why
            error = error_body(503, "the bridge is stopping")
            raise
        except ClientStalled as exc:  # the slot is freed: a stalled or vanished client holds it no longer
            log.warning("client %s: %s; closing it", client.peer, exc)
            error = error_body(408, str(exc))  # the HTTP API's code for a body that comes too slowly
        except Evicted as exc:  # a new connection took the slot from this silent one
            error = error_body(409, str(exc))
        except Exception as exc:  # a bug: this client is told and closed, the next is served
            log.exception("client %s: internal error", client.peer)
            error = error_body(500, f"internal error in the bridge ({type(exc).__name__}); it has been logged")
        finally:
            # the slot is freed before the teardown (the last status, the API stream, the socket
            # can take a while): a client that reconnects at once takes it, not refused, and its
            # session opens once this teardown is over (``closed``)
            client.left.set()
            if self._client is client:
                self._client = None
            try:
                if error is not None:
                    await client.tell(error)
                await close_stream(client.stream)
                await client.close()
                log.info("client %s disconnected", client.peer)
            finally:
                client.closed.set()
                self._tearing.discard(client)  # the bridge holds no gone client (its buffers, its stream)

    @property
    def teardown_bound(self) -> float:
        """Seconds a new connection waits with no earlier teardown ending: the API's frame cap
        (an answering API may take that long over the frame in flight) plus idle_timeout (its
        outputs past the cap, the session's close)."""
        return self.frame_cap + self.idle_timeout

    async def _torn_down(self, earlier: list[Connection]) -> None:
        """Until the teardown of every connection in ``earlier`` is over; ApiRefused (503) once
        teardown_bound passes with none of them over (the API does not answer their frames: a
        fixed bound from arrival would refuse the last of a storm of reconnects that is
        progressing). ``earlier`` is emptied: the client served holds none of them."""
        bound = self.teardown_bound
        try:
            while pending := [c for c in earlier if not c.closed.is_set()]:
                waits = [asyncio.ensure_future(c.closed.wait()) for c in pending]
                try:
                    done, _ = await asyncio.wait(waits, timeout=bound, return_when=asyncio.FIRST_COMPLETED)
                finally:
                    for w in waits:
                        w.cancel()
                if not done:
                    raise ApiRefused(
                        503,
                        f"the previous client's session did not close within {bound:g} s (the API's frame cap of "
                        f"{self.frame_cap:g} s plus the bridge's idle timeout of {self.idle_timeout:g} s): the API "
                        "is not answering; try again later",
                    )
        finally:
            earlier.clear()

    async def _serve(self, client: Connection) -> None:
        """Frames until the client leaves; its stream is left open on ``client`` (the caller
        closes it once the slot is free)."""
        async with self._api() as api:
            client.stream = await self._open(api)
            frame = 0
            while True:
                msg = await client.read()
                if msg is None:
                    continue
                points = await self._cloud(msg, client)
                if points is None:
                    continue
                too_large = self._too_large(points)
                if too_large is not None:  # answered as the API would, and the session is kept
                    log.warning("frame %d: %s", frame, too_large)
                    await self._frame_error(client, frame, 413, too_large, msg.version)
                else:
                    await self._frame(api, client, frame, points, msg.version)
                frame += 1

    async def _cloud(self, msg: p.Message, client: Connection) -> np.ndarray | None:
        if msg.device != self.device or msg.type not in ("POLYDATA", "POINT"):
            first = self._ignored.first((msg.type, msg.device))  # a warning the first time, then quietly
            self._throttle(
                logging.WARNING if first else logging.INFO,
                "ignored a %s message named %r (frames are POLYDATA or POINT named %r)",
                msg.type,
                msg.device,
                self.device,
            )
            return None
        # the body is the bridge's own buffer (Connection): a POLYDATA's points are decoded in it
        # its attributes are checked, not read: the bridge uses none
        decode = (
            functools.partial(p.decode_polydata, reuse=True, attributes=False)
            if msg.type == "POLYDATA"
            else p.decode_point
        )
        content, msg.content = msg.content, b""  # held here only: freed once its points are out
        try:
            if len(content) > _THREAD_DECODE:  # a large body's cells are read off the event loop
                decoded = await asyncio.to_thread(decode, content)
            else:
                decoded = decode(content)
        except p.ProtocolError as exc:
            await client.malformed(exc, msg.version)
            return None
        points = decoded.points if isinstance(decoded, p.PolyData) else decoded
        # OpenIGTLink carries float32, and the API reads packed float32 ("<f4"): sent as it came
        # in MessagePack (half the bytes of float64); JSON numbers are written from float64
        return np.asarray(points, np.float32 if self.encoding == "msgpack" else np.float64)


async def serve(bridge: Bridge, host: str, port: int, ready=None) -> None:
    """Serve until cancelled (Ctrl-C), then end the connections: each client is told, its
    session closed and its socket; ``ready`` (a callable) is told the bound port."""
    await bridge.prepare()
    loop = asyncio.get_running_loop()
    connections: set[asyncio.Task] = set()

    async def handled(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        connections.add(task)
        try:
            await bridge.handle(reader, writer)
        except asyncio.CancelledError:  # ended by serve (its teardown done): a task ending
            pass  # cancelled is logged with tracebacks by 3.11's StreamReaderProtocol
        finally:
            connections.discard(task)

    def connection() -> asyncio.StreamReaderProtocol:  # asyncio.start_server's, with a ConnectionReader
        return asyncio.StreamReaderProtocol(ConnectionReader(loop=loop), handled, loop=loop)

    try:
        server = await loop.create_server(connection, host, port)
    except socket.gaierror as exc:  # getaddrinfo's codes are not errno's: os.strerror(-2) is "Unknown error -2"
        raise BridgeError(f"cannot listen on {host}:{port}: the host does not resolve ({exc.strerror})") from None
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
    try:
        await asyncio.Future()  # served (create_server starts serving) until cancelled
    finally:
        server.close()  # no new client; not serve_forever's close, which on 3.12 waits for clients
        for task in connections:
            task.cancel()
        if connections:  # their teardown (a last status, the API stream) under a bound
            await asyncio.wait(connections, timeout=_STOP_GRACE)


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
    idle_timeout: float | None = None,
) -> int:
    """``elastreg igtl``: the bridge, over ``server`` or an API it starts in this process."""
    from contextlib import ExitStack

    with ExitStack() as stack:
        if server is None:
            from ..api.server import BackgroundServer
            from ..config import Settings, default_store

            api = stack.enter_context(BackgroundServer(Settings(store=store or default_store())))
            server = api.url
        bridge = Bridge(server, model, device=device, settings=settings, token=token, idle_timeout=idle_timeout)
        bridge.announce = lambda line: print(f"elastreg igtl: {line}", flush=True)

        def ready(bound: int) -> None:
            print(
                f"elastreg igtl: OpenIGTLink on {host}:{bound}, model {model!r}, API {server} "
                f"(frames: POLYDATA or POINT named {device!r})",
                flush=True,
            )

        try:  # Ctrl-C (KeyboardInterrupt, once the connections are ended) is the caller's
            asyncio.run(serve(bridge, host, port, ready))
        except BridgeError as exc:  # one line, as `elastreg serve` refuses a bad start
            print(f"error: {exc}", file=sys.stderr, flush=True)
            raise SystemExit(exc.exit_status) from None
    return 0

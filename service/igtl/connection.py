"""One OpenIGTLink client's connection: its messages read under a deadline once begun, its
answers sent under the API's deadline of progress, and a peer that left noticed even behind
unread bytes (its socket's TCP state, keepalive for one gone without a word)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import time
from typing import TYPE_CHECKING

from ..sendwait import Stalled, drop, progressing
from . import protocol as p
from .answers import error_body, status_message
from .lograte import Throttle

if TYPE_CHECKING:
    from clients.client import AsyncStream

log = logging.getLogger(__name__)

#: what a client that vanished without closing (cable pulled, laptop asleep) is probed with:
#: idle seconds, seconds between probes, probes unanswered before the connection is dropped
_KEEPALIVE = (60, 10, 6)
#: Linux's TCP states in which the peer has closed its side or the connection is over
#: (include/net/tcp_states.h: CLOSE, CLOSE_WAIT, LAST_ACK, CLOSING)
_PEER_CLOSED = frozenset((7, 8, 9, 11))


class ClientStalled(Exception):
    """A client began a message and did not finish it in time, took nothing of its answer for
    send_timeout, or vanished."""


class Evicted(Exception):
    """A client silent past the idle bound lost the slot to a new connection (:meth:`Connection.evict`)."""


class Connection:
    """One OpenIGTLink connection and what is its own: the header version it speaks and its API
    stream. Per connection, not on the Bridge: a client that leaves is torn down while the next
    is served, and its teardown must reach nothing of the next one's.

    ``send_timeout``, ``send_min_rate`` and ``read_timeout`` are the API's limits (see
    :class:`~.relay.Relay`): how long an answer may wait to be taken, and a message to come
    once begun."""

    def __init__(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        *,
        send_timeout: float,
        send_min_rate: float,
        read_timeout: float,
        throttle: Throttle | None = None,
    ) -> None:
        self.reader = reader
        self.writer = writer
        self.peer = writer.get_extra_info("peername")
        self.version = 1  # its header version (1 until its first message)
        self.stream: AsyncStream | None = None  # its API stream, while one is open
        #: set once it sends nothing more: it closed its side of the connection or lost it (what
        #: it sent before is still read, registered and answered), or its frames are over
        self.left = reader.ended if isinstance(reader, ConnectionReader) else asyncio.Event()
        #: set once its teardown is over: its frames answered, its API stream and socket closed
        self.closed = asyncio.Event()
        self.send_timeout = send_timeout
        self.send_min_rate = send_min_rate
        self.read_timeout = read_timeout
        #: what its malformed messages are logged through (the bridge's: shared by its clients)
        self.throttle = throttle or Throttle(log)
        self._socket = writer.get_extra_info("socket")
        self._quiet_since: float | None = time.monotonic()  # see quiet_since
        self._heard = 0  # bytes received when it fell quiet: past them it has spoken

    @property
    def quiet_since(self) -> float | None:
        """Since when it has sent nothing and had nothing answered (monotonic s; its connection at
        first); None while one of its messages is read or answered, or bytes it sent wait unread
        (a cloud sent while its session opens is no silence)."""
        if self._quiet_since is None or self._received() > self._heard:
            return None
        return self._quiet_since

    def _received(self) -> int:
        return self.reader.received if isinstance(self.reader, ConnectionReader) else 0

    def evict(self, why: str) -> None:
        """End a client that is waiting for its next message: its read raises Evicted(why), and
        it has left (``left``) at once, so the slot is free before its teardown."""
        self.reader.set_exception(Evicted(why))
        self.left.set()  # a ConnectionReader sets it too; a plain StreamReader does not

    def gone(self) -> bool:
        """Whether it has left (``left``), its socket's TCP state included: past 128 KiB unread
        the reader stops reading, and so never sees the close behind those bytes."""
        if not self.left.is_set() and peer_closed(self._socket):
            self.left.set()
        return self.left.is_set()

    def vanished(self) -> bool:
        """Whether it left with nothing to serve: closed with no byte unread, or lost (a reset).
        A TCP probe (`nc -z`, a health check) is so at once; one that sent a message and closed
        its side is not, and is answered."""
        return self.reader.at_eof() or self.reader.exception() is not None

    # -- in ----------------------------------------------------------------------------------

    async def read(self) -> p.Message | None:
        """The next message; None (answered or logged) when it is malformed or not for us.
        A client may be quiet between messages as long as it likes; once a message began, the
        rest must come within read_timeout (ClientStalled past it)."""
        if self._quiet_since is None:  # its last message answered (or ignored): silent from now
            # bytes already buffered are read at once, with no await in which to look at them
            self._quiet_since, self._heard = time.monotonic(), self._received()
        first = await self.reader.readexactly(1)
        self._quiet_since = None
        try:
            async with asyncio.timeout(self.read_timeout):
                return await self._read_rest(first)
        except TimeoutError:
            raise ClientStalled(f"no complete message within {self.read_timeout:g} s of its start") from None

    async def _read_rest(self, first: bytes) -> p.Message | None:
        reader = self.reader
        raw = first + await reader.readexactly(p.HEADER_SIZE - 1)
        try:
            version, mtype, device, ts, size, crc = p.parse_header(raw)
        except p.ProtocolError as exc:
            size = int.from_bytes(raw[42:50], "big")
            if size > p.MAX_BODY:  # cannot find the next message: the connection is lost
                await self.malformed(exc, self.version)
                raise ConnectionError(str(exc)) from None
            await self._discard(size)
            await self.malformed(exc, self.version)
            return None
        self.version = min(version, 2)
        body = await self._read_body(size)
        try:
            return p.parse_body(version, mtype, device, ts, body, crc)
        except p.ProtocolError as exc:
            await self.malformed(exc, version)
            return None

    async def _read_body(self, size: int) -> bytearray:
        """``size`` bytes in one buffer, grown as they come: readexactly held a large body twice
        (its reader's buffer grown to the whole body, then the bytes copied out of it), and a
        buffer of ``size`` made at once let a 58-byte header announcing 256 MiB cost 256 MiB."""
        body = bytearray()
        while len(body) < size:  # a large buffer grows in place (realloc), about 1.1x its bytes
            chunk = await self.reader.read(size - len(body))  # what is buffered, up to the reader's limit
            if not chunk:
                raise asyncio.IncompleteReadError(b"", size)
            body += chunk
        return body

    async def _discard(self, size: int) -> None:
        """Skip ``size`` bytes as they come, holding none (a body whose header is refused)."""
        while size > 0:
            chunk = await self.reader.read(size)
            if not chunk:
                raise asyncio.IncompleteReadError(b"", size)
            size -= len(chunk)

    # -- out ---------------------------------------------------------------------------------

    async def send(self, *messages: bytes) -> None:
        """Write ``messages`` and wait until the client has taken them. The deadline is one of
        progress (service.sendwait): a client that takes nothing for send_timeout, or takes an
        answer more slowly than send_min_rate, is ClientStalled (it would hold the only slot
        while it stays connected); one that keeps taking bytes (a large surface over a slow
        link) is waited for."""
        writer = self.writer
        for message in messages:
            writer.write(message)
        try:
            await progressing(writer.drain(), writer.transport, timeout=self.send_timeout, min_rate=self.send_min_rate)
        except Stalled as exc:
            drop(writer.transport)  # a status or a FIN would wait behind what it does not take
            raise ClientStalled(f"its answer: {exc}") from None

    async def malformed(self, exc: p.ProtocolError, version: int) -> None:
        """A malformed message's answer: its error in the shape a refused frame's has."""
        self.throttle(logging.WARNING, "malformed message: %s", exc)
        await self.send(status_message({"error": error_body(exc.code, str(exc))}, version))

    async def tell(self, error) -> None:
        """A last status (an ``error``) before the connection closes, under the send deadline;
        nothing to a client dropped for not taking its answers, or if it cannot go."""
        if self.writer.transport.is_closing():
            return
        with contextlib.suppress(Exception):
            await self.send(status_message({"error": error}, self.version))

    async def close(self) -> None:
        """Close the connection; one that does not take its last bytes within send_timeout is
        reset (sendwait.drop): closed plainly, the system would offer them to it for minutes."""
        writer = self.writer
        try:
            writer.close()
            await asyncio.wait_for(writer.wait_closed(), self.send_timeout)
        except Exception:
            with contextlib.suppress(Exception):
                drop(writer.transport)


class ConnectionReader(asyncio.StreamReader):
    """A StreamReader whose ``ended`` is set when its peer closes its side or the connection is
    lost, even while bytes it sent before are unread (at_eof() waits for those), and which
    counts the bytes ``received`` (a peer that sent bytes not read yet is not silent)."""

    def __init__(self, *, loop: asyncio.AbstractEventLoop) -> None:
        super().__init__(loop=loop)
        self.ended = asyncio.Event()
        self.received = 0  # bytes its peer has sent, read or not

    def feed_data(self, data: bytes) -> None:  # type: ignore[override]  # a transport feeds bytes
        self.received += len(data)
        super().feed_data(data)

    def feed_eof(self) -> None:
        self.ended.set()
        super().feed_eof()

    def set_exception(self, exc: Exception) -> None:
        self.ended.set()
        super().set_exception(exc)


def peer_closed(sock) -> bool:
    """Whether the socket's peer has closed (or the socket is gone), whatever is still unread;
    False where the system does not tell (no TCP_INFO)."""
    if sock is None or not hasattr(socket, "TCP_INFO"):
        return False
    try:
        state = sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 1)[0]
    except OSError:
        return True
    return state in _PEER_CLOSED


def keepalive(sock) -> None:
    """TCP keepalive on an accepted socket: a peer gone without a word is noticed (_KEEPALIVE)."""
    if sock is None:
        return
    with contextlib.suppress(OSError):
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
        for name, value in zip(("TCP_KEEPIDLE", "TCP_KEEPINTVL", "TCP_KEEPCNT"), _KEEPALIVE, strict=True):
            if hasattr(socket, name):  # Linux; elsewhere the system's defaults
                sock.setsockopt(socket.IPPROTO_TCP, getattr(socket, name), value)

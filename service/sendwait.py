"""Waiting for a peer to take what is sent to it: a deadline of progress, not of the whole message.

A client on a slow link may take a large message (a watcher's frame, a bridge's surface) for
longer than any fixed deadline while it keeps reading, and must be kept; one that stops reading,
or takes a byte now and then to look alive, must be let go, or it holds its socket, its slot
and the sender's buffers for ever. So a send waits while the bytes the peer has not taken
shrink: it fails once they have not shrunk for ``timeout`` seconds, or once the wait has lasted
``timeout`` plus the bytes it had to move at ``min_rate`` (a mean rate below which a peer is
as good as stalled). The API's streams and watchers and the OpenIGTLink bridge wait this way.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import struct
import sys
from collections.abc import Awaitable
from typing import Any, TypeVar

T = TypeVar("T")

#: seconds between looks at how much a peer has taken while a send waits on it
POLL_S = 0.1


class Stalled(TimeoutError):
    """The peer took nothing for the timeout, or took the bytes more slowly than the least rate."""


def untaken(transport: Any) -> int:
    """Bytes written to a transport that its peer has not taken: the transport's buffer and, on
    Linux, the socket's send queue (SIOCOUTQ: bytes the peer's system has not acknowledged),
    which on a slow link holds most of a message while the transport's buffer stays still for
    seconds (the kernel wakes the writer only once a third of its send buffer is free)."""
    n = transport.get_write_buffer_size()
    sock = transport.get_extra_info("socket")
    if sock is not None and sys.platform.startswith("linux"):
        import fcntl
        import termios

        with contextlib.suppress(OSError, ValueError):  # a socket closed meanwhile
            n += struct.unpack("i", fcntl.ioctl(sock.fileno(), termios.TIOCOUTQ, bytes(4)))[0]
    return n


async def progressing(aw: Awaitable[T], transport: Any, *, timeout: float, min_rate: float, size: int = 0) -> T:
    """``aw`` (a send or a drain on ``transport``), awaited while the peer takes bytes. Raises
    :class:`Stalled` (and cancels ``aw``) once the peer has taken nothing for ``timeout``
    seconds, or once the wait has lasted ``timeout`` plus its bytes at ``min_rate`` bytes a
    second; its bytes are those untaken when it began and ``size``, what ``aw`` will write."""
    loop = asyncio.get_running_loop()
    task = asyncio.ensure_future(aw)
    try:
        before = untaken(transport)
        start = since = loop.time()
        allowed = timeout + (before + size) / min_rate
        while not task.done():
            await asyncio.wait((task,), timeout=POLL_S)
            if task.done():
                break
            now, at = untaken(transport), loop.time()
            if now < before:  # the peer took bytes since the last look
                since = at
            before = now
            if at - since >= timeout:
                raise Stalled(f"took nothing for {timeout:g} s")
            if at - start >= allowed:
                raise Stalled(f"took too little in {at - start:.1f} s (under {min_rate:g} bytes a second)")
        return task.result()  # a connection lost meanwhile raises here
    finally:
        task.cancel()


def drop(transport: Any) -> None:
    """Close a stalled peer's connection at once, with a reset: its buffers are discarded (a
    close frame or a FIN would wait behind the bytes it does not take, and the system would go
    on offering them to it for minutes after the socket is closed)."""
    sock = transport.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError, ValueError):  # a socket closed meanwhile
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    transport.abort()

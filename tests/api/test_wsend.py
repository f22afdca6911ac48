"""A stream's or watcher's send under a deadline of progress (service/api/wsend.py): a client on
a slow link that keeps taking large messages is kept and gets each one whole, however long a
send waits behind the messages before it; one that stops reading is closed about
``send_timeout_s`` after its buffers fill, its connection dropped; one that takes a trickle
(below ``send_min_bytes_per_s``) is closed too.

Every client here is a real WebSocket client over a real loopback socket with a small window
and small segments (:class:`SlowSocket`), so the server's kernel buffers hold tens of kB, not
megabytes, and a slow reader backs the server's own buffer up within a second."""

from __future__ import annotations

import json
import logging
import math
import socket
import threading
import time

import httpx
import numpy as np
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from .conftest import MAX_POINTS, MSGPACK, mp, packed, start, wait_for

#: Linux's TCP state of a socket whose connection is over (a reset came): include/net/tcp_states.h
TCP_CLOSE = 7


class SlowSocket(socket.socket):
    """A client's socket on a slow link: a small window and small segments, and reads of 512
    bytes at about ``rate`` bytes a second for its first ``seconds`` of reading (at full speed
    after); ``rate`` 0 never reads."""

    def __init__(self, rate: float, seconds: float = math.inf) -> None:
        super().__init__()
        self.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 2048)  # before connect: a small window
        self.setsockopt(socket.IPPROTO_TCP, socket.TCP_MAXSEG, 536)  # keeps the server's send buffer small
        self.rate = rate
        self.seconds = seconds
        self.t0: float | None = None
        self.taken = 0

    def recv(self, n: int, flags: int = 0) -> bytes:
        self.t0 = self.t0 or time.monotonic()
        if time.monotonic() - self.t0 > self.seconds:
            chunk = super().recv(n, flags)
        elif self.rate == 0:
            threading.Event().wait()  # a frozen client: reads nothing, ever
            raise AssertionError
        else:
            chunk = super().recv(min(n, 512), flags)
            time.sleep(len(chunk) / self.rate)
        self.taken += len(chunk)
        return chunk

    def state(self) -> int:
        return self.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 1)[0]


def slow_client(server, path: str, sock: SlowSocket):
    """A WebSocket client of ``path`` over ``sock``."""
    sock.connect(("127.0.0.1", server.port))
    url = server.url.replace("http://", "ws://") + path
    return connect(url, sock=sock, max_size=1 << 24, compression=None, ping_interval=None, close_timeout=1)


def stream_frames(ws, support, clouds, n: int) -> None:
    """Open a stream and send ``n`` frames at once (pipelined), before any reply is read."""
    ws.send(json.dumps({"model": "bar", "support": support.tolist(), "max_iter": 2}))
    for t in range(n):
        ws.send(json.dumps({"points": clouds[t % len(clouds)].tolist(), "frame_id": t}))


def test_a_stream_client_that_takes_its_replies_slowly_is_kept(bar_store, support, clouds):
    """A stream's client on a slow link (25 kB/s for its first 4 s) sends 40 frames ahead: their
    replies (8 kB each, 330 kB in all) back up past the server's buffers, and a send waits
    about 2 s, twice send_timeout_s, for the client to take the 48 kB before it. It is kept,
    gets every reply in order, and its stream goes on. (A whole-send deadline closed it.)"""
    server = start(bar_store[0], instance_id="slowstream", send_timeout_s=1.0)
    try:
        n = 40
        sock = SlowSocket(rate=25e3, seconds=4.0)
        with slow_client(server, "/stream", sock) as ws:
            stream_frames(ws, support, clouds, n)
            assert "session" in json.loads(ws.recv(timeout=30))
            ids = []
            for _ in range(n):
                reply = json.loads(ws.recv(timeout=30))
                assert "error" not in reply, reply
                ids.append(reply["frame_id"])
            assert ids == list(range(n))
            ws.send(json.dumps({"points": clouds[0].tolist(), "frame_id": "after"}))
            assert json.loads(ws.recv(timeout=30))["frame_id"] == "after"
            assert sock.taken > 300e3
    finally:
        server.stop()


def big_frame(entry, seed: int) -> bytes:
    """A frame of MAX_POINTS points: its watchers' JSON message is about 170 kB."""
    rng = np.random.default_rng(seed)
    cloud = entry.mesh.nodes[rng.integers(0, entry.mesh.n_nodes, MAX_POINTS)]
    return mp({"points": packed(cloud + rng.normal(0, 1e-3, cloud.shape)), "frame_id": seed})


def test_a_watcher_that_takes_its_frames_slowly_is_kept(bar_store, support, entry):
    """A watcher on a slow link (40 kB/s for its first 5 s) of a session that solves two frames
    of 170 kB (JSON) at once: the second's send waits about 2 s, twice send_timeout_s, while
    the watcher takes the first. It is kept and gets both whole; a third frame reaches it
    after. (A whole-send deadline closed it after about 2 s.)"""
    server = start(bar_store[0], instance_id="slowwatch", send_timeout_s=1.0)
    try:
        with httpx.Client(base_url=server.url, timeout=60) as http:
            r = http.post("/sessions", json={"model": "bar", "support": support.tolist(), "max_iter": 2})
            sid = r.json()["session"]
            sock = SlowSocket(rate=40e3, seconds=5.0)
            with slow_client(server, f"/sessions/{sid}/watch", sock) as ws:
                assert json.loads(ws.recv(timeout=30))["watching"] == sid
                state = server.app.state
                assert wait_for(lambda: state.registry.get(sid, touch=False).watch.watchers == 1)
                for seed in (1, 2):
                    r = http.post(f"/sessions/{sid}/frames", content=big_frame(entry, seed), headers=MSGPACK)
                    assert r.status_code == 200
                got = [json.loads(ws.recv(timeout=30)) for _ in range(2)]
                assert [m["seq"] for m in got] == [1, 2]
                assert [m["result"]["frame_id"] for m in got] == [1, 2]
                assert all(len(m["points"]) == MAX_POINTS for m in got)
                assert sock.taken > 300e3
                r = http.post(f"/sessions/{sid}/frames", content=big_frame(entry, 3), headers=MSGPACK)
                assert json.loads(ws.recv(timeout=30))["seq"] == 3
    finally:
        server.stop()


def test_a_stream_client_that_stops_reading_is_dropped_after_send_timeout(bar_store, support, clouds):
    """A stream's client that reads nothing (frozen) while its replies back up is dropped about
    send_timeout_s after its buffers fill: its connection is reset (a close frame could not
    reach it) and its socket slot and session are freed at once, not at the next ping."""
    server = start(bar_store[0], instance_id="deafstream", send_timeout_s=1.0)
    try:
        sock, waited = frozen_stream_let_go(server, support, clouds)
        assert wait_for(lambda: sock.state() == TCP_CLOSE), "its connection was not dropped"
        assert 0.9 <= waited < 1.0 + LOOP_SLACK_S, f"let go {waited:.2f} s after its send stalled"
        sock.close()
    finally:
        server.stop()


def test_a_stream_client_that_takes_a_trickle_is_closed(bar_store, support, clouds):
    """A stream's client that keeps taking bytes, but at 4 kB/s, under the server's
    send_min_bytes_per_s (here 40 kB/s), is closed once a send has waited send_timeout_s plus
    its bytes at that rate (a few seconds here): taking a byte now and then does not hold a
    socket for ever. (Bounded by progress alone it was kept.)"""
    server = start(bar_store[0], instance_id="trickle", send_timeout_s=1.0, send_min_bytes_per_s=40e3)
    try:
        sock = SlowSocket(rate=4e3)
        t0 = time.monotonic()
        received = 0
        try:
            with slow_client(server, "/stream", sock) as ws:
                stream_frames(ws, support, clouds, 40)
                while time.monotonic() - t0 < 20:
                    ws.recv(timeout=20)
                    received += 1
        except (ConnectionClosed, TimeoutError, OSError):
            pass
        closed = time.monotonic() - t0
        assert wait_for(lambda: server.app.state.sockets == 0, timeout=5)
        assert closed < 15, f"a trickling client was kept {closed:.1f} s"
        assert received < 41 and sock.taken > 10e3  # it took bytes all along, not all of them
    finally:
        server.stop()


class HiddenSend:
    """An ASGI middleware outside the app that hands it a ``send`` of its own (a callable
    object, as a proxy or another server's may be): the app finds no transport behind it."""

    def __init__(self, app) -> None:
        self.app = app

    async def __call__(self, scope, receive, send) -> None:
        await self.app(scope, receive, _Forward(send))


class _Forward:
    def __init__(self, send) -> None:
        self.send = send

    async def __call__(self, message) -> None:
        await self.send(message)


def open_frozen(server, path: str) -> SlowSocket:
    """A WebSocket handshake for ``path`` over a socket that then never reads."""
    sock = SlowSocket(rate=0)
    sock.connect(("127.0.0.1", server.port))
    sock.sendall(
        f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n".encode()
        + b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
    )
    assert b" 101 " in socket.socket.recv(sock, 200)  # accepted; never read from again
    return sock


def send_frozen(sock: SlowSocket, support, clouds) -> None:
    """A stream's session config and 40 frames, whose replies back up."""
    frames = [{"model": "bar", "support": support.tolist(), "max_iter": 2}]
    frames += [{"points": clouds[t % len(clouds)].tolist(), "frame_id": t} for t in range(40)]
    for f in frames:
        sock.sendall(_client_frame(json.dumps(f).encode()))


def frozen_stream_let_go(server, support, clouds) -> tuple[SlowSocket, float]:
    """A stream client that sends its frames and never reads: its socket, once the server has
    freed its slot and its session, and the seconds from its last frame's solve to that. The
    reply of that frame is the send that stalled (the stream solves no more while it waits), so
    this is the wait the deadline bounds, whatever the solves before it took: on a loaded
    machine filling the buffers took seconds more, and a bound from the first frame failed."""
    state = server.app.state
    sock = open_frozen(server, "/stream")
    send_frozen(sock, support, clouds)
    solved, last, deadline = 0, time.monotonic(), time.monotonic() + 60
    while state.sockets and time.monotonic() < deadline:
        held = [h for h in list(state.registry._held.values()) if h.kind == "stream" and h.session is not None]
        frames = sum(h.session.frames for h in held)
        if frames > solved:  # only a rise: the count is gone once the session is
            solved, last = frames, time.monotonic()
        time.sleep(0.005)
    let_go = time.monotonic()
    assert not state.sockets, "the frozen client still holds its slot"
    assert solved, "no frame was solved"
    assert wait_for(lambda: len(state.registry) == 0)
    return sock, let_go - last


#: what a loaded machine (two cores, a load of 14) adds to the deadline between a stall and the
#: slot's release: the event loop's and the threads' turns, never seconds of solves
LOOP_SLACK_S = 2.0


def test_without_a_transport_a_frozen_stream_client_frees_its_slot(bar_store, support, clouds, caplog):
    """Where the app finds no transport (a wrapper of ``send`` outside it), a stream's frozen
    client is let go under the whole-send deadline, and so is the close that follows: the
    close frame would wait for ever behind the bytes it does not take, holding the handler,
    its socket slot and its session (held for good before). That the deadline of progress is
    off is logged, once."""
    caplog.set_level(logging.WARNING, logger="service.api.wsend")
    server = start(bar_store[0], wrap=HiddenSend, instance_id="hidden", send_timeout_s=1.0)
    try:
        state = server.app.state
        sock, waited = frozen_stream_let_go(server, support, clouds)
        assert 0.9 <= waited < 2 * 1.0 + LOOP_SLACK_S, waited  # the send's deadline whole, then the close's
        sock.close()
        open_frozen(server, "/stream").close()  # a second connection: not told again
        assert wait_for(lambda: state.sockets == 0)
        told = [r for r in caplog.records if "no transport to watch" in r.getMessage()]
        assert len(told) == 1, told
    finally:
        server.stop()


def test_under_uvicorns_trace_logging_a_frozen_stream_client_is_reset(bar_store, support, clouds, caplog):
    """uvicorn at log level trace wraps the app's ``send`` in its message logger: the transport
    is found behind it, so a frozen stream client is reset about send_timeout_s after its
    buffers fill and its slot and session freed, as at any other level (before: no transport,
    no reset: its connection stayed open behind the bytes it did not take)."""
    caplog.set_level(logging.WARNING, logger="service.api.wsend")
    server = start(bar_store[0], log_level="trace", instance_id="traced", send_timeout_s=1.0)
    for name in ("uvicorn.error", "uvicorn.asgi"):  # trace's lines: a dump of every message
        logging.getLogger(name).setLevel(logging.WARNING)
    try:
        sock, waited = frozen_stream_let_go(server, support, clouds)
        assert wait_for(lambda: sock.state() == TCP_CLOSE), "its connection was not dropped"
        assert 0.9 <= waited < 1.0 + LOOP_SLACK_S, f"let go {waited:.2f} s after its send stalled"
        assert not [r for r in caplog.records if "no transport to watch" in r.getMessage()]
        sock.close()
    finally:
        server.stop()


def test_without_a_transport_a_frozen_watcher_frees_its_slot_when_its_session_ends(bar_store, support, entry):
    """Where the app finds no transport, a watcher that stopped reading with a frame backed up
    in its buffers, whose session then ends, is let go once the close frame has waited
    send_timeout_s: its slot is freed (held for good before, the close waiting)."""
    server = start(bar_store[0], wrap=HiddenSend, instance_id="hiddenwatch", send_timeout_s=1.0)
    try:
        state = server.app.state
        with httpx.Client(base_url=server.url, timeout=60) as http:
            r = http.post("/sessions", json={"model": "bar", "support": support.tolist(), "max_iter": 2})
            sid = r.json()["session"]
            sock = open_frozen(server, f"/sessions/{sid}/watch")
            assert wait_for(lambda: state.registry.get(sid, touch=False).watch.watchers == 1)
            r = http.post(f"/sessions/{sid}/frames", content=big_frame(entry, 1), headers=MSGPACK)
            assert r.status_code == 200
            time.sleep(0.5)  # the frame (170 kB) goes out and backs up in front of the close
            assert http.delete(f"/sessions/{sid}").status_code in (200, 204)
            t0 = time.monotonic()
            assert wait_for(lambda: state.sockets == 0, timeout=15), "the frozen watcher still holds its slot"
            assert time.monotonic() - t0 < 5.0
        sock.close()
    finally:
        server.stop()


def _client_frame(payload: bytes) -> bytes:
    """A masked text frame (RFC 6455, as a client must send), the mask all zeros."""
    n = len(payload)
    head = bytes([0x81])
    if n < 126:
        head += bytes([0x80 | n])
    elif n < 1 << 16:
        head += bytes([0x80 | 126]) + n.to_bytes(2, "big")
    else:
        head += bytes([0x80 | 127]) + n.to_bytes(8, "big")
    return head + b"\0\0\0\0" + payload


def test_a_wrapper_whose_send_cell_is_empty_is_no_transport():
    """KeepTransport follows a wrapper's closure variable `send` to the protocol's; a wrapper
    whose cell of that name is not yet filled raised ValueError out of the middleware, failing
    every WebSocket before the app ran. It is no transport: the app runs, with the fallback."""
    import asyncio

    from service.api.wsend import TRANSPORT, KeepTransport

    def wrapped():
        async def wrapper(message):
            return await send(message)

        if False:  # makes `send` a cell of this scope, never filled
            send = None
        return wrapper

    seen = []

    async def app(scope, receive, send):
        seen.append(scope)

    asyncio.run(KeepTransport(app)({"type": "websocket"}, None, wrapped()))
    assert len(seen) == 1 and TRANSPORT not in seen[0]

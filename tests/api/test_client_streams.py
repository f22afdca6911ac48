"""The client's streams (clients/sockets.py) once closed, and misused, against the real
server: sync and async alike."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import hashlib
import re
import signal
import socket
import threading
import time
from collections.abc import Callable, Iterator

import pytest
from websockets.exceptions import ConnectionClosed

from clients import AsyncClient, Client, StreamError
from clients.bodies import config_body
from clients.sockets import AsyncStream, AsyncWatch, Stream, Watch

from .conftest import server_process


def test_a_closed_stream_keeps_raising_its_close_not_out_of_step(small, clouds):
    """A stream closed by the server (idle past the 2 s ttl of `small`: 1000 "idle for ...")
    raised that close at the next frame() only; the one after said "a frame's reply never came"
    with close_code None, as if a reply were pending. Every frame() now raises the close, and a
    stream closed by its own close() says so rather than "the server closed the stream"."""

    def idle(err: StreamError) -> None:  # the client's StreamError, not websockets' own exception
        assert err.status == 0 and err.close_code == 1000, (err, err.close_code)
        assert err.reason.startswith("idle for") and err.detail == err.reason
        assert str(err) == f"closed 1000: {err.reason}"
        assert isinstance(err.__cause__, ConnectionClosed)

    def own(err: StreamError) -> None:
        assert err.close_code == 1000 and "closed by its close()" in err.detail, (err, err.close_code)
        assert "server closed" not in err.detail

    async def main() -> None:
        async with AsyncClient(small.url) as aapi:
            with Client(small.url) as api, api.stream("bar") as sync_stream:
                sync_stream.frame(clouds[0])
                # opened only now: a first frame slower than the ttl (a loaded machine) would
                # close a stream opened before it, idle, before its own first frame
                async_stream = await aapi.stream("bar")
                await async_stream.frame(clouds[0])
                await asyncio.sleep(3.0)  # past the 2 s ttl, swept every 0.1 s
                for _ in range(3):
                    with pytest.raises(StreamError) as err:
                        sync_stream.frame(clouds[1])
                    idle(err.value)
                    with pytest.raises(StreamError) as err:
                        await async_stream.frame(clouds[1])
                    idle(err.value)
                await async_stream.close()
            with Client(small.url) as api:
                stream = api.stream("bar")
                stream.frame(clouds[0])
                stream.close()
                for _ in range(2):
                    with pytest.raises(StreamError) as err:
                        stream.frame(clouds[1])
                    own(err.value)
            async_stream = await aapi.stream("bar")
            await async_stream.frame(clouds[0])
            await async_stream.close()
            for _ in range(2):
                with pytest.raises(StreamError) as err:
                    await async_stream.frame(clouds[1])
                own(err.value)

    asyncio.run(main())


def test_frame_after_send_refuses_until_the_sent_frames_replies_are_received(live, support, clouds):
    """send() then frame(): frame() returned the sent frame's reply as its own (frame_id 1 for
    2), and every frame() after was one behind. It raises a StreamError while send()'s replies
    are to come; once recv() has taken them, frame() answers its own frame again."""
    with Client(live.url) as api, api.stream("bar", support=support) as s:
        s.send(clouds[0], frame_id="sent-1")
        s.send(clouds[1], frame_id="sent-2")
        with pytest.raises(StreamError, match=r"2 frame\(s\) sent with send\(\)") as err:
            s.frame(clouds[2], frame_id="framed")
        assert err.value.close_code is None
        assert s.recv()["frame_id"] == "sent-1"
        with pytest.raises(StreamError, match=r"1 frame\(s\) sent with send\(\)"):
            s.frame(clouds[2], frame_id="framed")
        assert s.recv()["frame_id"] == "sent-2"
        assert s.frame(clouds[2], frame_id="framed")["frame_id"] == "framed"
        assert s.frame(clouds[3], frame_id="next")["frame_id"] == "next"

    async def main() -> None:
        async with AsyncClient(live.url) as api, api.stream("bar", support=support) as s:
            await s.send(clouds[0], frame_id="sent")
            with pytest.raises(StreamError, match=r"1 frame\(s\) sent with send\(\)"):
                await s.frame(clouds[1], frame_id="framed")
            assert (await s.recv())["frame_id"] == "sent"
            assert (await s.frame(clouds[1], frame_id="framed"))["frame_id"] == "framed"

    asyncio.run(main())


def test_a_closed_stream_with_sent_frames_pending_raises_its_close(small, clouds):
    """send() then close() (or the server's close): frame() said "recv() them before frame()"
    with close_code None, recv() raised the close but left the count pending, and every frame()
    after said "recv() them" again, never the close. Every call now raises the close."""

    def own(err: StreamError) -> None:
        assert err.close_code == 1000 and "closed by its close()" in err.detail, (err, err.close_code)

    def idle(err: StreamError) -> None:
        assert err.close_code == 1000 and err.reason.startswith("idle for"), (err, err.close_code)

    with Client(small.url) as api:
        stream = api.stream("bar")
        stream.send(clouds[0])
        stream.close()
        for call in (lambda: stream.frame(clouds[1]), stream.recv, lambda: stream.frame(clouds[1])):
            with pytest.raises(StreamError) as err:
                call()
            own(err.value)
        with api.stream("bar") as stream:
            stream.send(clouds[0])
            time.sleep(3.5)  # its reply, then idle past the 2 s ttl: the server closes it
            for _ in range(2):
                with pytest.raises(StreamError) as err:
                    stream.frame(clouds[1])
                idle(err.value)

    async def main() -> None:
        async with AsyncClient(small.url) as api:
            stream = await api.stream("bar")
            await stream.send(clouds[0])
            await stream.close()
            for call in (lambda: stream.frame(clouds[1]), stream.recv, lambda: stream.frame(clouds[1])):
                with pytest.raises(StreamError) as err:
                    await call()
                own(err.value)
            stream = await api.stream("bar")
            await stream.send(clouds[0])
            await asyncio.sleep(3.5)
            for _ in range(2):
                with pytest.raises(StreamError) as err:
                    await stream.frame(clouds[1])
                idle(err.value)
            await stream.close()

    asyncio.run(main())


@contextlib.contextmanager
def frozen_api(store, path: str) -> Iterator[tuple[str, Callable[[], None], Callable[[], None]]]:
    """The real server: the URL of `path` on it, and how to freeze (SIGSTOP) and thaw it."""
    with server_process(store) as (server, url):
        yield (
            url.replace("http://", "ws://") + path,
            lambda: server.send_signal(signal.SIGSTOP),
            lambda: server.send_signal(signal.SIGCONT),
        )


@contextlib.contextmanager
def silent_peer() -> Iterator[tuple[str, Callable[[], None], Callable[[], None]]]:
    """A peer that completes a WebSocket handshake and then neither sends nor reads: the API
    frozen the moment it accepted. (The API's watch sends its first message at once, so a
    SIGSTOP after the handshake races it: under load the refusal came first.)"""
    listener = socket.create_server(("127.0.0.1", 0))
    held: list[socket.socket] = []

    def accept() -> None:
        while True:
            try:
                conn, _ = listener.accept()
            except OSError:  # closed: the test is over
                return
            held.append(conn)
            request = b""
            while b"\r\n\r\n" not in request:
                request += conn.recv(4096)
            key = re.search(rb"(?i)sec-websocket-key: *(\S+)", request).group(1)  # type: ignore[union-attr]
            proof = base64.b64encode(hashlib.sha1(key + b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11").digest())
            conn.sendall(
                b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                b"Sec-WebSocket-Accept: " + proof + b"\r\n\r\n"
            )

    threading.Thread(target=accept, daemon=True).start()
    try:
        yield f"ws://127.0.0.1:{listener.getsockname()[1]}/sessions/s-1/watch?encoding=msgpack", _nothing, _nothing
    finally:
        listener.close()
        for conn in held:
            conn.close()


def _nothing() -> None:
    pass


def assert_unanswered_opening_closes_at_once(peer, open_sync, open_async) -> None:
    """A peer that stops answering after the handshake (`peer`: its URL, how to freeze and thaw
    it): the opening, `open_sync(ws)` or `await open_async(ws)`, times out in its 1 s and closes
    at once, not after websockets' close_timeout (10 s) more for a closing handshake that will not
    come."""
    from websockets.asyncio.client import connect as aconnect
    from websockets.sync.client import connect

    with peer as (ws_url, freeze, thaw):
        with connect(ws_url, compression=None) as ws:
            freeze()
            started = time.monotonic()
            with pytest.raises(TimeoutError):
                open_sync(ws)
            took = time.monotonic() - started
        assert took < 3.0, f"took {took:.1f} s"
        thaw()

        async def main() -> float:
            ws = await aconnect(ws_url, compression=None)
            freeze()
            started = time.monotonic()
            with pytest.raises(TimeoutError):
                await open_async(ws)
            return time.monotonic() - started

        took = asyncio.run(main())
        thaw()
        assert took < 3.0, f"took {took:.1f} s"


def test_a_stream_whose_opening_goes_unanswered_closes_without_waiting(bar_store):
    """A server frozen (SIGSTOP) after the handshake, before it answered the stream's config: its
    close waited 10 s more. It closes at once now, sync and async."""
    config = config_body("bar", {})
    assert_unanswered_opening_closes_at_once(
        frozen_api(bar_store[0], "/stream"),
        lambda ws: Stream(ws, "msgpack", config, timeout=1.0),
        lambda ws: AsyncStream(ws, "msgpack", timeout=1.0)._open(config),
    )


def test_a_watch_whose_opening_goes_unanswered_closes_without_waiting():
    """As a stream's: a watch's first message unanswered left its close waiting 10 s after its
    own timeout. It closes at once now, sync and async."""
    assert_unanswered_opening_closes_at_once(
        silent_peer(),
        lambda ws: Watch(ws, "msgpack", timeout=1.0),
        lambda ws: AsyncWatch(ws, "msgpack", timeout=1.0)._open(),
    )

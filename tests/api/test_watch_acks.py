"""Acknowledging watchers (``{"ack": seq}`` on WS /sessions/{id}/watch): the server keeps at most
WINDOW frames unacknowledged, so a slow watcher gets the newest frame next instead of the backlog
its socket buffers hold; bad messages are answered and the watcher goes on; one that stops
acknowledging is closed after send_timeout_s; the client library's watch acknowledges; a watcher
that never acknowledges is served as before (beside it here, and in test_watch.py).

A watcher's mailbox holds one frame: one posted while its task still sends the frame before
(late on a loaded machine) overwrites the one between. So where a test expects exact seqs it
reads each frame before posting the next, as test_watch.py does."""

from __future__ import annotations

import json
import threading
import time

import httpx
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed

from service.api.watch import WINDOW

from .conftest import Live, mp, start, unpack, wait_for
from .test_watch import open_http, recv, watch

HANDLE_S = 0.2  # a slow watcher's time per frame: slower than the session's frames here
BURST = 40  # frames posted as fast as the server solves them


def ack(ws, seq: int, encoding: str = "json") -> None:
    ws.send(mp({"ack": seq}) if encoding == "msgpack" else json.dumps({"ack": seq}))


def post(http, sid: str, cloud: np.ndarray, frame_id=None) -> None:
    r = http.post(f"/sessions/{sid}/frames", json={"points": cloud.tolist(), "frame_id": frame_id})
    assert r.status_code == 200, r.text


def post_and_recv(http, sid: str, cloud: np.ndarray, frame_id, *watchers) -> list[int]:
    """Post a frame and the seq each watcher then receives (before the next can overwrite it)."""
    post(http, sid, cloud, frame_id)
    return [recv(ws)["seq"] for ws in watchers]


def stale_after(got: list[tuple[int, float]], t_end: float, newest: int) -> list[int]:
    """The seqs received after posting ended before the newest one."""
    return [seq for seq, t in got if t > t_end and seq < newest]


def test_the_window_holds_frames_until_they_are_acknowledged(live, http, support, clouds):
    """Exact: after ``{"ack": 0}`` two frames are sent and the rest wait (the newest kept); an
    ack sends the newest; the session's end sends the last frame and closes, window or not."""
    sid = open_http(http, support)
    with watch(live, sid) as ws:
        recv(ws)
        ack(ws, 0)
        assert [post_and_recv(http, sid, clouds[t], t, ws)[0] for t in range(WINDOW)] == [1, 2]
        for t in range(WINDOW, 4):
            post(http, sid, clouds[t], t)
        with pytest.raises(TimeoutError):
            ws.recv(timeout=0.5)  # frames 3 and 4 wait: the window is full
        ack(ws, 1)
        assert recv(ws)["seq"] == 4  # the newest; 3 was overwritten while it waited
        for t in range(4, 6):
            post(http, sid, clouds[t], t)
        with pytest.raises(TimeoutError):
            ws.recv(timeout=0.5)  # 2 and 4 are unacknowledged
        assert http.delete(f"/sessions/{sid}").status_code == 204
        assert recv(ws)["seq"] == 6  # the last published, as the session ended
        with pytest.raises(ConnectionClosed) as info:
            ws.recv(timeout=10)
        assert info.value.rcvd.code == 1000


def test_a_slow_acknowledging_watcher_skips_to_the_newest_frame(live, http, support, clouds):
    """A watcher that takes HANDLE_S per frame and acknowledges each is, once posting ends, at
    most WINDOW stale frames from the newest (without acks: the whole backlog, one by one);
    a watcher beside it that never acknowledges and keeps up gets every frame in order."""
    r = http.post("/sessions", json={"model": "bar", "support": support.tolist(), "max_iter": 2})
    sid = r.json()["session"]
    newest = BURST + 1
    with watch(live, sid) as slow, watch(live, sid, encoding="msgpack") as fast:
        recv(slow), recv(fast)
        ack(slow, 0)
        post(http, sid, clouds[0])  # one frame first: ack 0 is taken before the burst
        assert recv(slow)["seq"] == 1 and recv(fast)["seq"] == 1
        got: list[tuple[int, float]] = []

        def handle_slowly() -> None:
            seq = 1
            while seq < newest:
                time.sleep(HANDLE_S)
                ack(slow, seq)
                seq = recv(slow, timeout=60)["seq"]
                got.append((seq, time.monotonic()))

        reader = threading.Thread(target=handle_slowly, daemon=True)
        reader.start()
        t0 = time.monotonic()
        seqs = []
        for t in range(BURST):
            post(http, sid, clouds[t % len(clouds)], t)
            seqs.append(recv(fast)["seq"])
        t_end = time.monotonic()
        reader.join(timeout=60 + HANDLE_S * BURST)
        assert not reader.is_alive(), f"the slow watcher did not reach seq {newest}: {got}"
    stale = stale_after(got, t_end, newest)
    print(
        f"\nacknowledging watcher: {len(got)} frames of {BURST} posted in {t_end - t0:.1f} s; "
        f"after posting ended {len(stale)} stale ({stale}) before the newest, "
        f"{got[-1][1] - t_end:.2f} s later"
    )
    assert seqs == list(range(2, newest + 1))  # the non-acknowledging watcher: every frame, in order
    assert got[-1][0] == newest
    assert len(stale) <= WINDOW, f"{len(stale)} stale frames after posting ended: {stale}"
    assert len(got) < BURST, "the slow watcher should have skipped frames"
    http.delete(f"/sessions/{sid}")


def test_bad_messages_are_answered_and_the_watcher_goes_on(live, http, support, clouds):
    """Each bad message gets an error in the socket's encoding; the socket stays open, the
    window is as it was (not acknowledging yet: frames flow), and a map without ``ack`` (a
    token) is ignored."""
    sid = open_http(http, support)
    with watch(live, sid) as ws, watch(live, sid, encoding="msgpack") as wm:
        recv(ws), recv(wm)
        cases = [
            ("not json", 422, "JSON"),
            ("[1, 2]", 422, "maps"),
            ('{"ack": "1"}', 422, "integer"),
            ('{"ack": true}', 422, "integer"),
            ('{"ack": 1.0}', 422, "integer"),
            ('{"ack": 7}', 422, "not a frame sent"),
            ('{"ack": -1}', 422, "not a frame sent"),
            (json.dumps({"ack": 0, "pad": "x" * 70_000}), 413, "limit"),
        ]
        for bad, code, words in cases:
            ws.send(bad)
            err = recv(ws, timeout=10)["error"]
            assert err["code"] == code and words in err["detail"], (bad[:40], err)
        ws.send(json.dumps({"token": "again"}))  # no ack in it: ignored, no answer
        wm.send(mp({"ack": 5}))
        m = wm.recv(timeout=10)
        assert isinstance(m, bytes) and unpack(m)["error"]["code"] == 422
        wm.send(b"\xc1")  # not MessagePack
        assert unpack(wm.recv(timeout=10))["error"]["code"] == 422
        for t in range(3):  # neither has acknowledged: every frame comes, past WINDOW, as before acks
            assert post_and_recv(http, sid, clouds[t], t, ws, wm) == [t + 1, t + 1]
        ack(ws, 3)  # a good ack after bad ones is taken: the window is on
        ack(ws, 9)  # beyond what was sent: refused, the window as it was
        assert "not a frame sent" in recv(ws)["error"]["detail"]
        for t in range(3, 3 + WINDOW):
            assert post_and_recv(http, sid, clouds[t], t, ws, wm) == [t + 1, t + 1]
        for t in range(3 + WINDOW, 7):  # the window is full: only the watcher without acks gets these
            assert post_and_recv(http, sid, clouds[t % len(clouds)], t, wm) == [t + 1]
        with pytest.raises(TimeoutError):
            ws.recv(timeout=0.5)
    http.delete(f"/sessions/{sid}")


def test_a_watcher_that_stops_acknowledging_is_closed_and_frees_its_slot(bar_store, support, clouds):
    """A watcher that acknowledged once and then never again, while newer frames wait, is
    closed (1008) after send_timeout_s, as one that stops reading is, and its slot is free."""
    server = start(bar_store[0], instance_id="unacked", send_timeout_s=1.0)
    try:
        live = Live(server)
        with httpx.Client(base_url=server.url, timeout=60) as http:
            sid = open_http(http, support)
            with watch(live, sid) as ws:
                recv(ws)
                ack(ws, 0)
                assert [post_and_recv(http, sid, clouds[t], t, ws)[0] for t in range(WINDOW)] == [1, 2]
                t0 = time.monotonic()  # before the post: the wait for an ack starts inside it
                post(http, sid, clouds[WINDOW], WINDOW)  # waits: the window is full
                with pytest.raises(ConnectionClosed) as info:
                    ws.recv(timeout=10)
                assert info.value.rcvd.code == 1008 and "acknowledged" in info.value.rcvd.reason
                assert time.monotonic() - t0 >= 0.95  # send_timeout_s, less the clocks' granularity
            assert wait_for(lambda: server.app.state.sockets == 0, timeout=15)
            assert server.app.state.registry.get(sid, touch=False).watch.watchers == 0
    finally:
        server.stop()


@pytest.mark.parametrize("encoding", ["msgpack", "json"])
def test_the_client_library_watch_acknowledges_each_frame(live, http, support, clouds, encoding):
    """``Client.watch`` acknowledges a frame when the next is asked for: a consumer slower than
    the session reaches the newest frame at most WINDOW stale frames after posting ends, and
    iteration ends when the session does."""
    from clients import Client

    r = http.post("/sessions", json={"model": "bar", "support": support.tolist(), "max_iter": 2})
    sid = r.json()["session"]
    newest = BURST + 1
    with Client(live.url, encoding=encoding) as api, api.watch(sid) as frames:
        assert frames.session == sid and frames.model == "bar" and "matching" not in frames.config
        post(http, sid, clouds[0], "first")
        first = frames.recv()
        assert first["seq"] == 1 and first["result"]["frame_id"] == "first"
        assert isinstance(first["points"], np.ndarray)
        np.testing.assert_array_equal(first["points"], clouds[0])
        got: list[tuple[int, float]] = []

        def consume() -> None:
            for frame in frames:  # acknowledges the frame before each next one
                got.append((frame["seq"], time.monotonic()))
                time.sleep(HANDLE_S)

        consumer = threading.Thread(target=consume, daemon=True)
        consumer.start()
        for t in range(BURST):
            post(http, sid, clouds[t % len(clouds)], t)
        t_end = time.monotonic()
        assert wait_for(lambda: got and got[-1][0] == newest, timeout=30), got
        assert http.delete(f"/sessions/{sid}").status_code == 204
        consumer.join(timeout=15)
        assert not consumer.is_alive(), "iteration should end with the session"
    stale = stale_after(got, t_end, newest)
    assert len(stale) <= WINDOW, f"{len(stale)} stale frames after posting ended: {stale}"
    assert len(got) < BURST


def test_the_client_library_watch_of_an_unknown_session_is_refused(live):
    from clients import Client, StreamError

    with Client(live.url) as api, pytest.raises(StreamError) as info:
        api.watch("alpha-nosuchsession")
    assert info.value.status == 404 and info.value.close_code == 1008


def test_the_async_client_watch_acknowledges_each_frame(live, http, support, clouds):
    """``AsyncClient.watch``: frames 2 to 4 come while frame 1 is being handled; taking the next
    acknowledges 1, and the newest, 4, comes before the session ends: unacknowledged, the window
    (2 frames) would hold it to the end. Which of 2 and 3 comes between is the mailbox's: on a
    loaded machine a newer frame can overwrite one before the watcher's task sends it (seen:
    [1, 3, 4])."""
    import asyncio

    from clients import AsyncClient

    sid = open_http(http, support)

    async def main() -> list[int]:
        async with AsyncClient(live.url) as api:
            async with await api.watch(sid) as frames:
                assert frames.session == sid
                post(http, sid, clouds[0])
                seqs = [(await frames.recv())["seq"]]
                for t in range(1, 4):
                    post(http, sid, clouds[t], t)
                while seqs[-1] != 4:  # without acknowledgements this waits for the session's end
                    seqs.append((await asyncio.wait_for(frames.recv(), timeout=30))["seq"])
                http.delete(f"/sessions/{sid}")
                seqs += [frame["seq"] async for frame in frames]  # ends with the session
                return seqs

    seqs = asyncio.run(main())
    assert seqs[0] == 1 and seqs[-1] == 4 and seqs == sorted(set(seqs)), seqs  # [1, 2, 4] unloaded

"""One client at a time, as docs/frontends.md says: a second client while the first is connected
is refused (a 503 status, then closed) and the first goes on; a client that reconnects at once
(Slicer's connector toggled off and on, a client that dropped with a frame in flight) takes the
slot at once and is served once the old connection's frame is answered and its session closed:
one API session at a time, however fast a client reconnects."""

from __future__ import annotations

import asyncio
import json
import select
import signal
import socket
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from service.igtl import bridge as bridge_module
from service.igtl import protocol as p

from .conftest import get_mesh, is_open, point_frame, read_answer, read_message, registered, surface_cloud, wait_closed

REPO = Path(__file__).resolve().parents[2]


def test_a_second_client_while_one_is_connected_is_refused(api_server, run_bridge):
    """The second, while the first keeps sending frames, is sent a version-1 status {"error":
    {"code": 503, "detail"}} and closed; the first keeps its session."""
    api = api_server()
    mesh = get_mesh(api.url, "bar")
    n = len(mesh["surface_nodes"])
    frame = point_frame(surface_cloud(mesh))
    bridge = run_bridge(api.url)
    with bridge.connect() as first:
        first.sendall(frame)
        sid = registered(read_answer(first), n)["session"]
        with bridge.connect(timeout=30) as second:
            deadline = time.monotonic() + 30
            while not select.select([second], [], [], 0.1)[0]:  # frames from the first until told
                assert time.monotonic() < deadline, "the second client was never answered"
                first.sendall(frame)
                assert registered(read_answer(first), n)["session"] == sid
            msg = read_message(second)
            assert (msg.type, msg.device, msg.version) == ("STRING", "status", 1)
            assert json.loads(p.decode_string(msg.content)) == {
                "error": {"code": 503, "detail": "this bridge serves one client at a time; one is connected"}
            }
            with pytest.raises(ConnectionError):
                read_message(second)  # closed
        first.sendall(frame)
        assert registered(read_answer(first), n)["session"] == sid
    assert bridge.bridge.sessions == [sid]


def test_a_silent_client_gives_the_slot_to_a_new_connection_past_the_idle_timeout(api_server, run_bridge):
    """A client that connects and sends nothing (Slicer crashed with its connection half-open, a
    laptop asleep) held the only slot, and a reconnecting Slicer was refused: a new connection
    now waits until the silent one has sent nothing for idle_timeout, takes the slot and is
    served; the silent one is told (409) and closed, its session with it."""
    idle = 1.5
    api = api_server()
    mesh = get_mesh(api.url, "bar")
    frame = point_frame(surface_cloud(mesh))
    bridge = run_bridge(api.url, idle_timeout=idle)
    with bridge.connect() as silent:
        old_sid = bridge.wait_sessions(1)[0]
        t0 = time.monotonic()
        with bridge.connect() as new:
            new.sendall(frame)
            status = registered(read_answer(new), len(mesh["surface_nodes"]))
            served = time.monotonic() - t0
            assert status["session"] != old_sid
            assert served < idle + 5.0, f"served {served:.1f} s after it connected"
            error = json.loads(p.decode_string(read_message(silent).content))["error"]
            assert error["code"] == 409 and "sent nothing for" in error["detail"], error
            with pytest.raises(ConnectionError):
                read_message(silent)  # closed
            wait_closed(api.url, old_sid)
            new.sendall(frame)  # and the new client keeps the slot
            assert registered(read_answer(new), len(mesh["surface_nodes"]))["session"] == status["session"]


def test_a_connection_that_closes_at_once_evicts_no_silent_client(api_server, run_bridge):
    """A TCP probe (`nc -z`, a health check) connects and closes while the client holding the slot
    is quiet between clouds: past idle_timeout that client keeps its slot and its session, is
    told nothing, and the bridge opens no session for the probe."""
    idle = 1.5
    api = api_server()
    mesh = get_mesh(api.url, "bar")
    bridge = run_bridge(api.url, idle_timeout=idle)
    with bridge.connect() as quiet:
        sid = bridge.wait_sessions(1)[0]
        socket.create_connection(("127.0.0.1", bridge.port)).close()
        assert not select.select([quiet], [], [], idle + 2.0)[0], "the quiet client was told something"
        quiet.sendall(point_frame(surface_cloud(mesh)))
        assert registered(read_answer(quiet), len(mesh["surface_nodes"]))["session"] == sid
    assert bridge.bridge.sessions == [sid]


def test_a_client_that_reconnects_at_once_is_served(api_server, run_bridge, monkeypatch):
    """Closing a session here waits until the test lets it (as an API slow to answer the close
    would): a client that closes and connects again at once takes the slot, not refused, and is
    served over a new session once the old session is closed; the new one goes on."""
    api = api_server()
    mesh = get_mesh(api.url, "bar")
    n = len(mesh["surface_nodes"])
    frame = point_frame(surface_cloud(mesh))
    close_stream = bridge_module.close_stream
    release = threading.Event()  # an event, not a sleep: a loaded machine may serve slowly

    async def slow_close(stream) -> None:
        await asyncio.to_thread(release.wait, 60)
        await close_stream(stream)

    monkeypatch.setattr(bridge_module, "close_stream", slow_close)
    bridge = run_bridge(api.url)
    with bridge.connect() as old:
        old.sendall(frame)
        old_sid = registered(read_answer(old), n)["session"]
    with bridge.connect() as new:  # at once, while the old session is being closed
        new.sendall(frame)
        new.settimeout(1.0)
        with pytest.raises(TimeoutError):  # one session at a time: the old one's close first
            new.recv(1)
        assert bridge.bridge.busy and is_open(api.url, old_sid)
        release.set()
        new.settimeout(60)
        new_sid = registered(read_answer(new), n)["session"]
        assert new_sid != old_sid and not is_open(api.url, old_sid)
        new.sendall(frame)
        after = registered(read_answer(new), n)
        assert after["session"] == new_sid and after["frame_id"] == 1
    assert bridge.bridge.sessions == [old_sid, new_sid]


def test_a_client_that_dropped_with_a_frame_in_flight_is_served_when_it_reconnects(api_server, run_bridge):
    """A client sends a frame and closes without its answer, then connects again at once: the
    bridge is still registering the old frame (or opening the old session) and not yet reading,
    yet the new connection is served, not refused; the old session is closed after."""
    api = api_server()
    mesh = get_mesh(api.url, "bar")
    n = len(mesh["surface_nodes"])
    frame = point_frame(surface_cloud(mesh))
    bridge = run_bridge(api.url)
    for tries in range(1, 4):
        with bridge.connect() as old:
            old.sendall(frame)
        with bridge.connect() as new:
            new.sendall(frame)
            sid = registered(read_answer(new), n)["session"]
            (old_sid,) = set(bridge.wait_sessions(2 * tries)[-2:]) - {sid}  # the two opened in either order
            wait_closed(api.url, old_sid)
            assert is_open(api.url, sid)
        wait_closed(api.url, sid)


def test_a_reconnect_is_served_while_the_old_connection_holds_unread_frames(api_server, run_bridge, monkeypatch):
    """A frame in flight for 3 s with two 1,000-point clouds (272 KB) sent behind it: the old
    connection's reader stops reading past 128 KiB buffered, so the client's close was never seen
    and its reconnect was refused after the 1 s grace (the review's repro). The socket's own
    state tells the close."""
    api = api_server()
    mesh = get_mesh(api.url, "bar")
    n = len(mesh["surface_nodes"])
    small, big = point_frame(surface_cloud(mesh)), point_frame(surface_cloud(mesh, n=1000))
    frame = bridge_module.Bridge._frame

    async def slow_frame(self, *args, **kwargs):
        await asyncio.sleep(3.0)  # a frame in flight as long as a cold Newton frame
        return await frame(self, *args, **kwargs)

    monkeypatch.setattr(bridge_module.Bridge, "_frame", slow_frame)
    bridge = run_bridge(api.url)
    with bridge.connect() as old:
        old.sendall(small)
        bridge.wait_sessions(1)
        old.sendall(big + big)
    with bridge.connect() as new:  # at once
        new.sendall(small)
        sid = registered(read_answer(new), n)["session"]
    assert sid in bridge.bridge.sessions[1:]


def test_a_storm_of_reconnects_holds_one_session_at_a_time(api_server, run_bridge):
    """Connect, send a frame, close at once, again and again (the review's storm): each new
    connection waits for the old one's frame and session close before its own session opens, so
    the API holds one or two of the bridge's sessions at any time, not one per connection, and a
    client that comes after is served."""
    api = api_server()
    mesh = get_mesh(api.url, "bar")
    frame = point_frame(surface_cloud(mesh, n=2000))  # a frame that takes the solver a while
    bridge = run_bridge(api.url)
    peak, stop = [0], threading.Event()

    def watch() -> None:  # the API's open sessions, as its /health counts them
        with httpx.Client(timeout=10) as http:
            while not stop.is_set():
                peak[0] = max(peak[0], http.get(f"{api.url}/health").json()["sessions"]["open"])
                time.sleep(0.01)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    try:
        for _ in range(20):
            with bridge.connect() as sock:
                sock.sendall(frame)
                time.sleep(0.05)
        with bridge.connect() as sock:
            sock.sendall(frame)
            registered(read_answer(sock), len(mesh["surface_nodes"]))
    finally:
        stop.set()
        watcher.join()
    assert peak[0] <= 2, f"{peak[0]} sessions open at once"


def test_a_client_that_sent_its_cloud_while_its_session_opens_is_not_silent(api_process, run_bridge):
    """The API (its own process) is stopped (SIGSTOP), so client A's session is still opening
    when A sends its cloud; B connects and stays silent. A has spoken: it keeps the slot and is
    answered once the API goes on, and B is refused (503), as docs/frontends.md says of a holder
    that sent a message first. A was evicted as "silent" (409) and its frame never answered."""
    url, server = api_process
    mesh = get_mesh(url, "bar")
    bridge = run_bridge(url, idle_timeout=1.0)
    server.send_signal(signal.SIGSTOP)
    try:
        a = bridge.connect()
        a.sendall(point_frame(surface_cloud(mesh)))
        time.sleep(0.5)
        with bridge.connect(timeout=10) as b:  # silent
            msg = read_message(b)
            assert json.loads(p.decode_string(msg.content))["error"]["code"] == 503
            time.sleep(1.5)  # past A's idle timeout, had it been silent
    finally:
        server.send_signal(signal.SIGCONT)
    with a:
        status = registered(read_answer(a), len(mesh["surface_nodes"]))
        assert status["frame_id"] == 0


@pytest.mark.parametrize("api_process", [{"ELASTREG_MAX_TIME_BUDGET_MS": "1000"}], indirect=True)
def test_a_reconnect_behind_a_frame_the_api_never_answers_is_refused_within_the_bound(api_process, run_bridge):
    """The API is stopped (SIGSTOP) with A's frame in flight; A closes and B connects at once. B's
    session waits for A's frame and session close, which a stopped API never gives: B waited with
    no word (47 s measured). Now B gets a 503 within the API's frame cap (1 s here) plus
    idle_timeout and is closed, and so does the next (it waits for A too, not for B alone); once
    the API goes on, A's session closes and C is served, the only session opened since A's."""
    idle, bound = 2.0, 3.0
    url, server = api_process
    mesh = get_mesh(url, "bar")
    n = len(mesh["surface_nodes"])
    frame = point_frame(surface_cloud(mesh))
    bridge = run_bridge(url, idle_timeout=idle)
    with bridge.connect() as a:
        a.sendall(frame)
        a_sid = registered(read_answer(a), n)["session"]
        server.send_signal(signal.SIGSTOP)
        a.sendall(frame)  # in flight while the API is stopped
        time.sleep(0.3)
    try:
        for _ in range(2):
            bridge.wait_free()
            t0 = time.monotonic()
            with bridge.connect(timeout=bound + 10) as b:
                b.sendall(frame)
                msg = read_message(b)
                waited = time.monotonic() - t0
                error = json.loads(p.decode_string(msg.content))["error"]
                assert error["code"] == 503, error
                assert (
                    "did not close within 3 s (the API's frame cap of 1 s plus the bridge's idle timeout of 2 s)"
                    in (error["detail"])
                ), error
                assert bound - 0.5 < waited < bound + 5, f"refused {waited:.1f} s after it connected"
                with pytest.raises(ConnectionError):
                    read_message(b)  # closed
    finally:
        server.send_signal(signal.SIGCONT)
    wait_closed(url, a_sid, timeout=60)
    bridge.wait_free()
    with bridge.connect() as c:
        c.sendall(frame)
        c_sid = registered(read_answer(c), n)["session"]
    assert bridge.bridge.sessions == [a_sid, c_sid]


@pytest.mark.parametrize(
    "api_process", [{"store": REPO / "model_store", "ELASTREG_MAX_TIME_BUDGET_MS": "2000"}], indirect=True
)
def test_a_reconnect_behind_a_fem_frame_at_the_api_cap_is_served(api_process, run_bridge):
    """A phantom FEM frame that runs to the API's frame cap (2 s here, status time_limit) is in
    flight when A closes and B connects. The API is answering, only slowly: B was refused at the
    idle timeout (1 s) as if it were not (the review's repro: refused at 10 s, A answered 0.1 s
    later). Now B waits up to the cap plus the idle timeout and is served."""
    idle = 1.0
    url, _ = api_process
    mesh = get_mesh(url, "phantom")
    n = len(mesh["surface_nodes"])
    cloud = surface_cloud(mesh, n=1500) + np.float32([0.0, 0.0, 0.004])  # displaced 4 mm: real FEM work
    bridge = run_bridge(url, "phantom", settings={"method": "fem"}, idle_timeout=idle)
    with bridge.connect() as a:
        a.sendall(point_frame(cloud))
        status = registered(read_answer(a), n)
        assert status["status"] == "time_limit", status  # a frame that runs to the cap
        a_sid = status["session"]
        a.sendall(point_frame(cloud * np.float32(1.001)))  # in flight for about the cap
        time.sleep(0.2)
    t0 = time.monotonic()
    with bridge.connect(timeout=30) as b:
        b.sendall(point_frame(cloud))
        status = registered(read_answer(b), n)
    waited = time.monotonic() - t0
    assert waited > idle, f"served {waited:.1f} s after it connected: A's frame was not in flight that long"
    assert status["session"] != a_sid and not is_open(url, a_sid)
    assert bridge.bridge.sessions == [a_sid, status["session"]]

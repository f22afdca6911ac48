"""Graceful shutdown: when the server is told to stop, the frames already being solved finish
and are answered (HTTP and WebSocket), the frames a stream still had queued get a 503 error
each, streams close with 1012 (service restart), and no new connection is taken."""

from __future__ import annotations

import concurrent.futures
import json
import threading

import httpx
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from .conftest import mp, occupied, packed, start, unpack, wait_for


def test_shutdown_answers_the_frames_in_flight(bar_store, support, clouds):
    server = start(bar_store[0], instance_id="drain", solver_threads=1, solve_queue=4, drain_timeout_s=20)
    pool, registry = server.app.state.pool, server.app.state.registry
    stopper = threading.Thread(target=server.stop)
    try:
        with httpx.Client(base_url=server.url, timeout=60) as http, concurrent.futures.ThreadPoolExecutor(1) as ex:
            sid = http.post("/sessions", json={"model": "bar", "support": support.tolist()}).json()["session"]
            ws = connect(server.url.replace("http://", "ws://") + "/stream")
            ws.__enter__()
            ws.send(mp({"model": "bar", "support": packed(support, "<i8")}))
            stream_sid = unpack(ws.recv(timeout=30))["session"]
            with occupied(pool, 1) as release:
                for t in range(4):  # frame 0 is admitted and waits for the thread; 1-3 wait in the stream
                    ws.send(mp({"points": packed(clouds[t]), "frame_id": t}))
                assert wait_for(lambda: registry.get(stream_sid).busy == 1)
                posted = ex.submit(
                    lambda: httpx.post(
                        f"{server.url}/sessions/{sid}/frames", json={"points": clouds[0].tolist()}, timeout=60
                    )
                )
                assert wait_for(lambda: pool.in_flight == 3)
                stopper.start()
                assert wait_for(lambda: pool.draining)
                with pytest.raises(httpx.ConnectError):  # the listening socket is closed
                    httpx.get(server.url + "/health", timeout=5)
                release.set()
            replies = [unpack(ws.recv(timeout=60)) for _ in range(4)]
            assert replies[0]["frame_id"] == 0 and "converged" in replies[0]  # solved and answered
            assert [r["error"]["code"] for r in replies[1:]] == [503] * 3
            assert [r["error"]["retry_after"] for r in replies[1:]] == [1] * 3  # a restart, or another replica
            assert [r["error"]["frame_id"] for r in replies[1:]] == [1, 2, 3]
            with pytest.raises(ConnectionClosed) as closed:
                ws.recv(timeout=30)
            assert closed.value.rcvd.code == 1012
            r = posted.result(timeout=60)
            assert r.status_code == 200 and json.loads(r.content)["status"]
    finally:
        if not stopper.is_alive() and stopper.ident is None:
            server.stop()
        stopper.join(timeout=60)
    assert not server.thread.is_alive()

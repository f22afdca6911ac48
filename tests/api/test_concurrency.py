"""Concurrent streams give the results of the same frames run one at a time; the event loop
stays free while every solver thread is busy; HTTP frames of one session never interleave."""

from __future__ import annotations

import concurrent.futures
import json
import threading
import time

import httpx
import numpy as np
from websockets.sync.client import connect

from .conftest import mp, packed, unpack


def run_stream(url: str, config: dict, frames: list[np.ndarray], binary: bool) -> list[dict]:
    with connect(url) as ws:
        ws.send(mp(config) if binary else json.dumps(config))
        ws.recv(timeout=30)
        out = []
        for t, pts in enumerate(frames):
            ws.send(
                mp({"points": packed(pts), "frame_id": t})
                if binary
                else json.dumps({"points": pts.tolist(), "frame_id": t})
            )
            m = ws.recv(timeout=120)
            out.append(unpack(m) if isinstance(m, bytes) else json.loads(m))
        return out


def test_concurrent_streams_match_one_at_a_time(live, support, clouds):
    jobs = []
    for i in range(6):  # different supports, orders and encodings per stream
        s = support[i % 3 :: 1 + i % 2]
        order = [clouds[(i + t) % len(clouds)] for t in range(5)]
        config = {
            "model": "bar",
            "support": s.tolist(),
            "outputs": ["displacement", "forces"],
            "method": "fem" if i == 5 else "network",
            "max_iter": 40,
        }
        jobs.append((config, order, i % 2 == 0))
    alone = [run_stream(live.ws, *job) for job in jobs]
    with concurrent.futures.ThreadPoolExecutor(len(jobs)) as ex:
        together = list(ex.map(lambda job: run_stream(live.ws, *job), jobs))
    for a, b in zip(alone, together, strict=True):
        assert [r["frame_id"] for r in b] == list(range(5))
        for ra, rb in zip(a, b, strict=True):
            np.testing.assert_array_equal(np.asarray(ra["displacement"]), np.asarray(rb["displacement"]))
            np.testing.assert_array_equal(np.asarray(ra["forces"]), np.asarray(rb["forces"]))
            assert ra["iterations"] == rb["iterations"]


def test_health_answers_while_every_solver_thread_is_busy(live, http, support, clouds):
    """Solves run in the pool, never on the event loop: with every solver thread held by a
    long job (a stand-in for long FEM frames), /health still answers at once, and a frame
    queued meanwhile is served when a thread frees up."""
    pool = live.app.state.pool
    release = threading.Event()
    blockers = [pool._pool.submit(release.wait, 30) for _ in range(pool.threads)]
    try:
        with concurrent.futures.ThreadPoolExecutor(1) as ex:

            def frame():  # opening a session and its frame both wait for a solver thread
                with httpx.Client(base_url=live.url, timeout=60) as c:
                    s = c.post("/sessions", json={"model": "bar", "support": support.tolist()}).json()["session"]
                    return c.post(f"/sessions/{s}/frames", json={"points": clouds[0].tolist()})

            pending = ex.submit(frame)
            for _ in range(5):
                t0 = time.perf_counter()
                assert http.get("/health").status_code == 200
                assert http.get("/models/bar").status_code == 200
                assert time.perf_counter() - t0 < 0.5
            assert not pending.done()  # still waiting for a solver thread
            release.set()
            assert pending.result(timeout=60).status_code == 200
    finally:
        release.set()
        for b in blockers:
            b.result(timeout=30)


def test_http_frames_of_one_session_run_one_at_a_time(live, http, support, clouds):
    sid = http.post("/sessions", json={"model": "bar", "support": support.tolist()}).json()["session"]

    def post(t):
        with httpx.Client(base_url=live.url, timeout=60) as c:
            return c.post(f"/sessions/{sid}/frames", json={"points": clouds[t % len(clouds)].tolist(), "frame_id": t})

    with concurrent.futures.ThreadPoolExecutor(6) as ex:
        replies = list(ex.map(post, range(12)))
    assert all(r.status_code == 200 for r in replies)
    assert sorted(r.json()["frame_id"] for r in replies) == list(range(12))
    assert http.get(f"/sessions/{sid}").json()["counters"]["frames"] == 12
    http.delete(f"/sessions/{sid}")

"""Admission control (API.md, "Access"): a saturated server answers a fast 503 with Retry-After
(HTTP) or a 503 error for that frame with retry_after (the stream goes on) instead of queueing
without bound; every 503, the session limit's too, says when to retry; work for a closed session
or a gone client is dropped, not computed; a session whose solve outlives its client keeps its
slot until the solve ends; non-finite results are never converged; /health says degraded (503)
when the solve queue is full or no model loaded. The solver threads are held by jobs admitted as
solves are (``occupied``), standing in for long FEM frames."""

from __future__ import annotations

import concurrent.futures
import json
import time

import httpx
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from clients import ApiError, Client, StreamError
from service.api.server import BackgroundServer
from service.api.sessions import RegistryFull
from service.api.work import flag_non_finite
from service.config import Settings

from .conftest import MSGPACK, Live, mp, occupied, packed, recv, start, wait_for, ws_url


@pytest.fixture(scope="module")
def narrow(bar_store):
    """One solver thread, one place in its queue, no HTTP frame waiting behind another of its
    session, two sessions at most (a 503 at that limit says: retry in 3 s)."""
    server = start(
        bar_store[0],
        instance_id="narrow",
        solver_threads=1,
        solve_queue=1,
        session_queue=0,
        max_sessions=2,
        session_retry_after_s=3,
    )
    yield Live(server)
    server.stop()


@pytest.fixture
def api(narrow):
    with httpx.Client(base_url=narrow.url, timeout=60) as c:
        yield c
    registry = narrow.app.state.registry
    for sid in list(registry._held):  # every test leaves the server empty
        registry.close(sid)
    assert wait_for(lambda: registry.closing == 0 and narrow.app.state.pool.in_flight == 0)


def test_a_saturated_server_answers_503_at_once(narrow, api, clouds):
    sid = api.post("/sessions", json={"model": "bar", "max_iter": 20}).json()["session"]
    pool = narrow.app.state.pool
    with connect(ws_url(narrow)) as ws:
        ws.send(mp({"model": "bar", "max_iter": 20}))
        recv(ws)
        with occupied(pool, pool.threads + pool.queue):  # every thread and queue place taken
            for body, headers in [
                (json.dumps({"points": clouds[0].tolist()}).encode(), {"content-type": "application/json"}),
                (mp({"points": packed(clouds[0])}), MSGPACK),
            ]:
                t0 = time.perf_counter()
                r = api.post(f"/sessions/{sid}/frames", content=body, headers=headers)
                assert r.status_code == 503 and r.headers["retry-after"] == "1"
                assert time.perf_counter() - t0 < 2.0  # refused, not queued
            health = api.get("/health")
            assert health.status_code == 503 and health.json()["status"] == "degraded"
            assert health.headers["retry-after"] == "1"
            assert "saturated" in health.json()["reasons"][0]
            ws.send(mp({"points": packed(clouds[0]), "frame_id": 1}))
            err = recv(ws)["error"]
            assert err["code"] == 503 and err["frame_id"] == 1
            assert api.post("/sessions", json={"model": "bar"}).status_code == 503  # opening needs a thread too
        ws.send(mp({"points": packed(clouds[1]), "frame_id": 2}))  # the stream went on
        assert recv(ws)["frame_id"] == 2
    assert api.get("/health").json()["status"] == "ok"
    r = api.post(f"/sessions/{sid}/frames", json={"points": clouds[1].tolist()})
    assert r.status_code == 200 and api.get(f"/sessions/{sid}").json()["counters"]["frames"] == 1


def test_the_client_hands_a_503s_retry_after_to_its_caller(narrow, api, clouds):
    """A load-test or frontend backs off by the server's word: ApiError.retry_after."""
    pool = narrow.app.state.pool
    with Client(narrow.url) as client, client.open_session("bar", max_iter=20) as s:
        with occupied(pool, pool.threads + pool.queue), pytest.raises(ApiError) as err:
            s.frame(clouds[0])
        assert err.value.status == 503 and err.value.retry_after == 1.0
        with pytest.raises(ApiError) as err:  # a refusal that is not about load carries none
            s.frame(np.zeros((3, 2)))
        assert err.value.status == 422 and err.value.retry_after is None
        s.frame(clouds[1])  # the session goes on
        assert s.info()["counters"]["frames"] == 1


def close_code(ws) -> int:
    with pytest.raises(ConnectionClosed) as info:
        while True:
            ws.recv(timeout=10)
    return info.value.rcvd.code


def test_a_streams_503_says_when_to_retry(narrow, api, clouds):
    """A frame refused for load, and a stream refused at opening for want of a thread, carry
    retry_after (the HTTP 503's Retry-After, seconds); the first goes on, the second closes with
    1013 (try again later), not 1008 (a bad config)."""
    pool = narrow.app.state.pool
    with connect(ws_url(narrow)) as ws, connect(ws_url(narrow)) as late:
        ws.send(mp({"model": "bar", "max_iter": 20}))
        recv(ws)
        with occupied(pool, pool.threads + pool.queue):
            ws.send(mp({"points": packed(clouds[0]), "frame_id": 7}))
            err = recv(ws)["error"]
            assert err == {"code": 503, "detail": err["detail"], "frame_id": 7, "retry_after": 1}
            late.send(mp({"model": "bar"}))  # building its session needs a thread
            err = recv(late)["error"]
            assert err["code"] == 503 and err["retry_after"] == 1
            assert close_code(late) == 1013
        ws.send(mp({"points": np.zeros((3, 2)).tolist(), "frame_id": 8}))  # not about load: none
        err = recv(ws)["error"]
        assert err["code"] == 422 and "retry_after" not in err
        ws.send(mp({"points": packed(clouds[1]), "frame_id": 9}))
        assert recv(ws)["frame_id"] == 9


def test_the_client_hands_a_streams_retry_after_to_its_caller(narrow, api, clouds):
    """Stream.frame raises StreamError with retry_after, as the HTTP path's ApiError has it."""
    pool = narrow.app.state.pool
    with Client(narrow.url) as client, client.stream("bar", max_iter=20) as s:
        with occupied(pool, pool.threads + pool.queue), pytest.raises(StreamError) as err:
            s.frame(clouds[0], frame_id=1)
        assert err.value.status == 503 and err.value.retry_after == 1.0 and err.value.frame_id == 1
        assert err.value.close_code is None  # the stream goes on
        with pytest.raises(StreamError) as err:
            s.frame(np.zeros((3, 2)))
        assert err.value.status == 422 and err.value.retry_after is None
        assert s.frame(clouds[1], frame_id=2)["frame_id"] == 2


def test_the_session_limit_503_says_when_to_retry(narrow, api):
    """At max_sessions, POST /sessions is a 503 with Retry-After (session_retry_after_s, not the
    solve pool's retry_after_s), a stream's first message a 503 error with retry_after and a
    close with 1013; the client gives both to its caller as retry_after."""
    for _ in range(narrow.settings.max_sessions):
        assert api.post("/sessions", json={"model": "bar"}).status_code == 201
    r = api.post("/sessions", json={"model": "bar"})
    assert r.status_code == 503 and r.headers.get("retry-after") == "3"  # narrow's, not retry_after_s (1)
    assert "maximum of 2 sessions" in r.json()["detail"] and "retry in 3 s" in r.json()["detail"]
    with connect(ws_url(narrow)) as ws:
        ws.send(mp({"model": "bar"}))
        err = recv(ws)["error"]
        assert err["code"] == 503 and err["retry_after"] == 3
        assert close_code(ws) == 1013
    with Client(narrow.url) as client:
        with pytest.raises(ApiError) as http_err:
            client.open_session("bar")
        assert http_err.value.status == 503 and http_err.value.retry_after == 3.0
        with pytest.raises(StreamError) as stream_err:
            client.stream("bar")
        assert stream_err.value.status == 503 and stream_err.value.retry_after == 3.0
        assert stream_err.value.close_code == 1013


def test_frames_of_one_session_wait_no_deeper_than_session_queue(narrow, api, clouds):
    sid = api.post("/sessions", json={"model": "bar", "max_iter": 20}).json()["session"]
    with concurrent.futures.ThreadPoolExecutor(1) as ex:
        with occupied(narrow.app.state.pool, 1):
            first = ex.submit(api.post, f"/sessions/{sid}/frames", json={"points": clouds[0].tolist()})
            held = narrow.app.state.registry.get(sid)
            assert wait_for(lambda: held.busy == 1)  # admitted, waiting for the thread
            r = api.post(f"/sessions/{sid}/frames", json={"points": clouds[1].tolist()})
            assert r.status_code == 503 and "waiting" in r.json()["detail"]
        assert first.result(timeout=60).status_code == 200


def test_a_closed_sessions_waiting_frame_is_dropped_not_solved(narrow, api, clouds):
    sid = api.post("/sessions", json={"model": "bar", "max_iter": 20}).json()["session"]
    held = narrow.app.state.registry.get(sid)
    pool = narrow.app.state.pool
    dropped = pool.dropped
    with occupied(pool, 1) as release, concurrent.futures.ThreadPoolExecutor(1) as ex:
        waiting = ex.submit(api.post, f"/sessions/{sid}/frames", json={"points": clouds[0].tolist()})
        assert wait_for(lambda: held.busy == 1)
        assert api.delete(f"/sessions/{sid}").status_code == 204
        release.set()
        r = waiting.result(timeout=60)
    assert r.status_code == 404 and "dropped" in r.json()["detail"]
    assert held.session.frames == 0 and pool.dropped == dropped + 1


def test_a_gone_http_clients_frame_is_dropped(narrow, api, clouds):
    sid = api.post("/sessions", json={"model": "bar", "max_iter": 20}).json()["session"]
    held = narrow.app.state.registry.get(sid)
    pool = narrow.app.state.pool
    dropped = pool.dropped
    with occupied(pool, 1):
        with pytest.raises(httpx.ReadTimeout):  # the client gives up and closes its connection
            httpx.post(f"{narrow.url}/sessions/{sid}/frames", json={"points": clouds[0].tolist()}, timeout=1.0)
        time.sleep(0.3)
    assert wait_for(lambda: pool.in_flight == 0 and held.busy == 0)
    assert held.session.frames == 0 and pool.dropped == dropped + 1


def test_a_gone_streams_queued_frames_are_dropped_and_its_slot_is_held_until_its_solve_ends(narrow, api, clouds):
    registry, pool = narrow.app.state.registry, narrow.app.state.pool
    dropped = pool.dropped
    ws = connect(ws_url(narrow))
    ws.__enter__()
    ws.send(mp({"model": "bar", "max_iter": 20}))
    sid = recv(ws)["session"]
    held = registry.get(sid)
    with occupied(pool, 1) as release:
        for t in range(4):
            ws.send(mp({"points": packed(clouds[t]), "frame_id": t}))
        assert wait_for(lambda: held.busy == 1)  # frame 0 admitted, waiting for the thread
        ws.close()
        # the client has gone: its session is closed, but frame 0 still holds a place in the pool
        assert wait_for(lambda: registry.closing == 1)
        assert api.get(f"/sessions/{sid}").status_code == 404
        # it still counts against the limit of 2: one more session fits, a second does not
        first = registry.reserve("http")
        with pytest.raises(RegistryFull):
            registry.reserve("http")
        registry.cancel(first)
        release.set()
        assert wait_for(lambda: registry.closing == 0)
    assert held.session.frames == 0 and pool.dropped == dropped + 1  # nothing solved for it
    assert api.post("/sessions", json={"model": "bar"}).status_code == 201


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # the overflow is the point
def test_non_finite_results_are_never_converged(live, http, support, clouds):
    """Points at 1e200 m, which overflowed the objective, are now refused (past the model's
    reach); a cloud 5 m above the bar, within it, folds elements: the frame says so, and the
    session's next frame is what it would have been without it."""
    sid = http.post("/sessions", json={"model": "bar", "support": support.tolist()}).json()["session"]
    ref = http.post("/sessions", json={"model": "bar", "support": support.tolist()}).json()["session"]
    r = http.post(f"/sessions/{sid}/frames", json={"points": (clouds[0] * 1e200).tolist()})
    assert r.status_code == 422 and "too far from the model" in r.text
    r = http.post(f"/sessions/{sid}/frames", json={"points": (clouds[0] + [0.0, 0.0, 5.0]).tolist()})
    assert r.status_code == 200
    body = r.json()
    assert body["converged"] is False and body["status"] == "non_finite"
    a = http.post(f"/sessions/{sid}/frames", json={"points": clouds[1].tolist()}).json()
    b = http.post(f"/sessions/{ref}/frames", json={"points": clouds[1].tolist()}).json()
    np.testing.assert_allclose(a["forces"], b["forces"], rtol=1e-9, atol=1e-12)
    payload = {
        "converged": True,
        "status": "converged",
        "message": "",
        "objective": 1.0,
        "displacement": np.array([[0.0, np.nan, 0.0]]),
    }
    flag_non_finite(payload)
    assert payload["converged"] is False and payload["status"] == "non_finite" and "displacement" in payload["message"]


def test_health_is_degraded_without_a_model(tmp_path):
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "manifest.json").write_text(json.dumps({"format_version": 1, "id": "broken"}))
    with BackgroundServer(Settings(store=tmp_path, blas_threads=0)) as server:
        r = httpx.get(server.url + "/health")
        assert r.status_code == 503 and r.json()["status"] == "degraded" and r.json()["models"] == 0
        assert "no model" in r.json()["reasons"][0] and "broken" in r.json()["skipped_models"]

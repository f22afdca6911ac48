"""WS /stream: the config handshake, frames in order (JSON text and MessagePack binary), error
messages that leave the stream and its state intact, 1008 for a bad first message, garbage,
skip_stale, and the session's end with its socket."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from service.registration.session import Session, SessionConfig

from .conftest import MAX_POINTS, mp, packed, unpack


def recv(ws, timeout=60):
    m = ws.recv(timeout=timeout)
    return unpack(m) if isinstance(m, bytes) else json.loads(m)


def close_code(ws) -> int:
    with pytest.raises(ConnectionClosed) as info:
        ws.recv(timeout=10)
    return info.value.rcvd.code


def test_json_stream_in_order_matches_in_process(live, entry, support, clouds):
    ref = Session(entry.network, SessionConfig(support=tuple(support.tolist())))
    with connect(live.ws) as ws:
        assert ws.response.headers["x-elastreg-instance"] == "alpha"
        ws.send(json.dumps({"model": "bar", "support": support.tolist()}))
        opened = ws.recv(timeout=30)
        assert isinstance(opened, str)
        opened = json.loads(opened)
        assert opened["session"].startswith("alpha-") and opened["config"]["support"] == support.tolist()
        for t, pts in enumerate(clouds):  # pipelined: every frame sent before any result is read
            ws.send(json.dumps({"points": pts.tolist(), "frame_id": t}))
        for t, pts in enumerate(clouds):
            r = ws.recv(timeout=60)
            assert isinstance(r, str)
            r = json.loads(r)
            want = ref.frame(pts)
            assert r["frame_id"] == t and "skipped" not in r
            np.testing.assert_allclose(r["displacement"], want.outputs["displacement"], rtol=1e-9, atol=1e-14)
            np.testing.assert_allclose(r["forces"], want.outputs["forces"], rtol=1e-9, atol=1e-12)


def test_msgpack_stream_replies_in_each_messages_kind(live, support, clouds):
    with connect(live.ws) as ws:
        ws.send(mp({"model": "bar", "support": packed(support, "<i8"), "outputs": ["forces", "stress"]}))
        opened = ws.recv(timeout=30)
        assert isinstance(opened, bytes) and isinstance(unpack(opened)["config"]["support"], np.ndarray)
        t0 = time.perf_counter()
        ws.send(mp({"points": packed(clouds[0]), "frame_id": "a"}))
        r = ws.recv(timeout=60)
        round_trip_ms = 1e3 * (time.perf_counter() - t0)
        assert isinstance(r, bytes)
        r = unpack(r)
        assert r["frame_id"] == "a" and r["forces"].shape == (support.size, 3) and r["stress"].ndim == 1
        # the reply's own encoding was timed: more than nothing, less than the round trip
        assert "displacement" not in r and 0 < r["timing_ms"]["encode"] < round_trip_ms
        ws.send(json.dumps({"points": clouds[1].tolist(), "frame_id": "b"}))  # a text frame: a text reply
        r = ws.recv(timeout=60)
        assert isinstance(r, str) and json.loads(r)["frame_id"] == "b"


BAD_FRAMES = [
    (b"\xc1\xc1 garbage \x00\xff", 422, "MessagePack"),
    ("garbage {[", 422, "JSON"),
    ("", 422, "JSON"),
    ('{"points": [[NaN, 0, 0]], "frame_id": 3}', 422, "NaN"),
    (json.dumps({"points": [[1, 2]], "frame_id": "x"}), 422, "(m, 3)"),
    # a cloud in millimetres against the bar in metres, and one 1e20 m off (once converged)
    (json.dumps({"points": [[1000.0, 500.0, 1000.0], [4000.0, 0.0, 0.0]]}), 422, "millimetres"),
    (json.dumps({"points": [[1e20, 1e20, 1e20]], "frame_id": "far"}), 422, "too far from the model"),
    # a cloud in metres against a model in millimetres: the bar 1,000x smaller, inside its box
    (json.dumps({"points": (1e-3 * np.eye(4, 3)).tolist()}), 422, "in metres while the model is in millimetres"),
    (json.dumps({"points": [[1, 2, 3]], "support": [0]}), 422, "fixed"),
    (json.dumps({"points": [[1, 2, 3]], "support": [1.5]}), 422, "integers"),
    (json.dumps({"points": [[1, 2, 3]], "support": []}), 422, "non-empty"),
    (json.dumps({"frame_id": 4}), 422, "Field required"),
    (json.dumps([1, 2, 3]), 422, "map"),
    (json.dumps({"model": "bar"}), 422, "points"),
    (mp({"points": {"dtype": "<f8", "shape": [5, 3], "data": b"\0" * 8}}), 422, "bytes"),
    (mp({"points": packed(np.zeros((MAX_POINTS + 1, 3)))}), 413, "limit"),
    (bytes(range(256)) * 4, 422, "MessagePack"),
    (b"\xc1", 422, "not valid MessagePack: a byte that starts no"),  # msgpack's bare errors, in words
    (b"\x81\xa1a" * 5000 + b"\xc0", 422, "not valid MessagePack: lists and maps nested too deep"),
    # a large body that does not decode is not parsed a second time (on the event loop) for its id
    ('{"frame_id": "big", "points": [[NaN, 0, 0]' + ", [0, 0, 0]" * 20_000 + "]}", 422, "NaN"),
]


def test_bad_frames_get_error_messages_and_the_stream_goes_on(live, entry, support, clouds):
    ref = Session(entry.network, SessionConfig(support=tuple(support.tolist())))
    with connect(live.ws) as ws:
        ws.send(json.dumps({"model": "bar", "support": support.tolist()}))
        recv(ws)
        for k, (message, code, words) in enumerate(BAD_FRAMES):
            ws.send(message)
            r = recv(ws)
            assert set(r) == {"error"}, (k, r)
            assert r["error"]["code"] == code and words in r["error"]["detail"], (k, r)
            if k == 3:
                assert r["error"]["frame_id"] == 3  # a small body read again, leniently, for its id
            if k == 4:
                assert r["error"]["frame_id"] == "x"  # decoded once: its id from that decode
            if k == len(BAD_FRAMES) - 1:
                assert r["error"].get("frame_id") is None
            pts = clouds[k % len(clouds)]
            ws.send(json.dumps({"points": pts.tolist(), "frame_id": k}))
            good = recv(ws)
            want = ref.frame(pts)
            assert good["frame_id"] == k
            np.testing.assert_allclose(good["forces"], want.outputs["forces"], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize(
    "first, code",
    [
        (b"\x00\x01\x02garbage", 422),
        ("{not json", 422),
        (json.dumps({"model": "nope"}), 404),
        (json.dumps({"model": "bar", "alpha": -1}), 422),
        (json.dumps({"model": "bar", "support": [0]}), 422),
        (json.dumps(["bar"]), 422),
        (json.dumps({"points": [[0, 0, 0]]}), 422),
    ],
)
def test_bad_first_message_closes_with_1008(live, http, first, code):
    with connect(live.ws) as ws:
        ws.send(first)
        r = recv(ws)
        assert r["error"]["code"] == code and r["error"]["detail"]
        assert close_code(ws) == 1008
    assert http.get("/health").status_code == 200  # and the server is fine


def test_closing_the_socket_ends_the_session(live, http):
    with connect(live.ws) as ws:
        ws.send(json.dumps({"model": "bar"}))
        sid = recv(ws)["session"]
        assert http.get(f"/sessions/{sid}").status_code == 200
    deadline = time.monotonic() + 10
    while http.get(f"/sessions/{sid}").status_code != 404 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert http.get(f"/sessions/{sid}").status_code == 404


def test_client_vanishing_mid_solve(live, http, support, clouds):
    """A socket dropped with frames in flight: the server finishes, drops the session, goes on."""
    for _ in range(3):
        ws = connect(live.ws).__enter__()  # closed by hand below, mid-solve
        ws.send(json.dumps({"model": "bar", "method": "fem", "support": support.tolist()}))
        recv(ws)
        for pts in clouds:
            ws.send(json.dumps({"points": pts.tolist()}))
        ws.close()
    deadline = time.monotonic() + 30
    while http.get("/health").json()["sessions"]["stream"] and time.monotonic() < deadline:
        time.sleep(0.05)
    assert http.get("/health").json()["sessions"]["stream"] == 0


def test_skip_stale_solves_the_newest(live, support, clouds):
    smaller = support[::2]
    with connect(live.ws) as ws:
        ws.send(
            json.dumps(
                {
                    "model": "bar",
                    "method": "fem",
                    "max_iter": 30,
                    "support": support.tolist(),
                    "skip_stale": True,
                    "outputs": ["forces"],
                }
            )
        )
        assert recv(ws)["config"]["skip_stale"] is True
        n = 8
        for t in range(n):
            body = {"points": clouds[t % len(clouds)].tolist(), "frame_id": t}
            if t == 2:
                body["support"] = smaller.tolist()  # applies even if frame 2 is skipped
            ws.send(json.dumps(body))
        results = []
        while not results or results[-1]["frame_id"] != n - 1:
            results.append(recv(ws))
        ids = [r["frame_id"] for r in results]
        assert ids == sorted(ids) and len(results) < n  # fewer results than frames: some skipped
        assert sum(r["skipped"] for r in results) + len(results) == n
        seen = sorted(ids + [i for r in results for i in r["skipped_ids"]])
        assert seen == list(range(n))
        assert results[-1]["support"] == smaller.tolist()


def test_without_skip_stale_every_frame_is_answered(live, support, clouds):
    with connect(live.ws) as ws:
        ws.send(json.dumps({"model": "bar", "method": "fem", "max_iter": 30, "support": support.tolist()}))
        recv(ws)
        for t in range(8):
            ws.send(json.dumps({"points": clouds[t % len(clouds)].tolist(), "frame_id": t}))
        assert [recv(ws)["frame_id"] for _ in range(8)] == list(range(8))


def test_stream_at_the_session_limit_closes_with_1013(small):
    url = small.url.replace("http://", "ws://") + "/stream"
    with connect(url) as a, connect(url) as b:
        for ws in (a, b):
            ws.send(json.dumps({"model": "bar"}))
            assert "session" in recv(ws)
        with connect(url) as c:
            c.send(json.dumps({"model": "bar"}))
            assert recv(c)["error"]["code"] == 503
            assert close_code(c) == 1013


def _behind_a_busy_worker(ws, support, clouds, queued: list[dict], until) -> tuple[list[dict], list[dict]]:
    """Opens a skip_stale Newton stream on `ws`, keeps its worker busy with four frames, sends
    `queued` behind them and reads replies up to the one for frame `until`: (replies, errors)."""
    config = {"model": "bar", "method": "fem", "max_iter": 30, "support": support.tolist(), "skip_stale": True}
    ws.send(json.dumps(config))
    recv(ws)
    for t in range(4):  # keeps the worker busy while the queued frames wait
        ws.send(json.dumps({"points": clouds[t % len(clouds)].tolist(), "frame_id": t}))
    for body in queued:
        ws.send(json.dumps(body))
    replies: list[dict] = []
    while not replies or replies[-1].get("frame_id") != until:
        replies.append(recv(ws))
    return replies, [r["error"] for r in replies if "error" in r]


def test_skip_stale_answers_the_newest_good_frame_when_the_last_is_refused(live, support, clouds):
    """The newest queued frame's support is refused: it gets its own error, and the newest good
    frame before it is answered in its place, with its support, which then stands."""
    other = support[:-2].tolist()
    with connect(live.ws) as ws:
        queued = [
            {"points": clouds[1].tolist(), "frame_id": "moved", "support": other},
            {"points": clouds[0].tolist(), "frame_id": "bad", "support": [10_000]},
        ]
        replies, errors = _behind_a_busy_worker(ws, support, clouds, queued, until="moved")
        assert [(e["frame_id"], e["code"]) for e in errors] == [("bad", 422)], errors
        assert replies[-1]["support"] == other
        ws.send(json.dumps({"points": clouds[2].tolist(), "frame_id": "next"}))
        assert recv(ws)["support"] == other


def test_skip_stale_refuses_a_skipped_frames_bad_support_under_its_own_id(live, support, clouds):
    """Skipped or not, a frame whose support the session cannot take gets its own error; the
    next frame runs on the support that stood."""
    with connect(live.ws) as ws:
        queued = [
            {"points": clouds[0].tolist(), "frame_id": "bad", "support": [10_000]},
            {"points": clouds[1].tolist(), "frame_id": "good"},
        ]
        replies, errors = _behind_a_busy_worker(ws, support, clouds, queued, until="good")
        assert [(e["frame_id"], e["code"]) for e in errors] == [("bad", 422)], errors
        assert "0..80" in errors[0]["detail"]
        assert replies[-1]["support"] == support.tolist()

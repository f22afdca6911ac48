"""Every documented error (404, 409, 413, 415, 422, 503 and the stream's error message) leaves
the session working, with its state unchanged: after each refused request the next good frame
gives exactly what a session that never saw the bad one gives."""

from __future__ import annotations

import json

import numpy as np
import pytest

from service.registration.session import Session, SessionConfig

from .conftest import MAX_POINTS, MSGPACK, mp, packed


def _bad_frames(entry, support):
    interior = np.setdiff1d(np.flatnonzero(entry.mesh.free_mask), entry.region)
    pts = [[0.0, 0.0, 0.0], [1.0, 0.5, 1.0]]
    nan = np.array(pts)
    nan[0, 0] = np.nan
    inf = np.array(pts)
    inf[1, 2] = np.inf
    j = {"content-type": "application/json"}
    cases = [
        # (name, headers, body bytes, status, words in the detail)
        ("missing points", j, json.dumps({"frame_id": 1}), 422, "Field required"),
        ("wrong shape", j, json.dumps({"points": [[1.0, 2.0]]}), 422, "(m, 3)"),
        ("flat points", j, json.dumps({"points": [1.0, 2.0, 3.0]}), 422, "(m, 3)"),
        ("empty points", j, json.dumps({"points": []}), 422, "(m, 3)"),
        ("ragged points", j, json.dumps({"points": [[1, 2, 3], [1, 2]]}), 422, "regular array"),
        ("string coordinate", j, json.dumps({"points": [[1, 2, "3"]]}), 422, "numbers"),
        ("null coordinate", j, json.dumps({"points": [[1, 2, None]]}), 422, "numbers"),
        ("NaN literal", j, '{"points": [[NaN, 0, 0]]}', 422, "NaN"),
        ("Infinity literal", j, '{"points": [[Infinity, 0, 0]]}', 422, "NaN and Infinity"),
        ("overflowing number", j, '{"points": [[1e999, 0, 0]]}', 422, "a JSON number is out of range"),
        ("integer of 400 digits", j, f'{{"points": [[{10**400}, 0, 0]]}}', 422, "a JSON number is out of range"),
        ("frame id of 400 digits", j, f'{{"points": {pts}, "frame_id": {10**400}}}', 422, "out of range"),
        ("a point 1e300 m off", j, json.dumps({"points": [*pts, [1e300, 0.0, 0.0]]}), 422, "the farthest 1e+300 m"),
        ("a point past floats", j, json.dumps({"points": [*pts, [1.7e308, -1.7e308, 0.0]]}), 422, "beyond float"),
        ("a boolean coordinate", j, json.dumps({"points": [[True, 0.0, 0.0], *pts]}), 422, "not booleans"),
        ("a boolean in msgpack", MSGPACK, mp({"points": [[0.0, 0.0, False], *pts]}), 422, "not booleans"),
        ("boolean dtype", MSGPACK, mp({"points": {"dtype": "|b1", "shape": [1, 3], "data": b"\1\0\1"}}), 422, "dtype"),
        ("NaN packed", MSGPACK, mp({"points": packed(nan)}), 422, "NaN or infinite"),
        ("inf listed in msgpack", MSGPACK, mp({"points": inf.tolist()}), 422, "NaN or infinite"),
        ("node id out of range", j, json.dumps({"points": pts, "support": [10_000]}), 422, "0..80"),
        ("fixed node", j, json.dumps({"points": pts, "support": [0]}), 422, "fixed"),
        ("boolean node id", j, json.dumps({"points": pts, "support": [True, 5]}), 422, "not booleans"),
        ("outside the region", j, json.dumps({"points": pts, "support": interior[:1].tolist()}), 422, "region"),
        ("float node id", j, json.dumps({"points": pts, "support": [70.0]}), 422, "integers"),
        ("string node id", j, json.dumps({"points": pts, "support": ["70"]}), 422, "numbers"),
        ("boolean node id", j, json.dumps({"points": pts, "support": [True]}), 422, "integers"),
        ("negative node id", j, json.dumps({"points": pts, "support": [-3]}), 422, "non-negative"),
        ("empty support", j, json.dumps({"points": pts, "support": []}), 422, "non-empty"),
        ("repeated support", j, json.dumps({"points": pts, "support": [70, 70]}), 422, "repeats"),
        (
            "packed float ids",
            MSGPACK,
            mp({"points": packed(np.array(pts)), "support": packed(np.array([70.0]))}),
            422,
            "integers",
        ),
        ("unknown field", j, json.dumps({"points": pts, "colour": "red"}), 422, "Extra inputs"),
        # past the model's reach: millimetres against metres, and 1e20 m off (once converged)
        ("cloud in millimetres", j, json.dumps({"points": (1e3 * np.array(pts)).tolist()}), 422, "millimetres"),
        ("cloud 1e20 m off", j, json.dumps({"points": (np.array(pts) + 1e20).tolist()}), 422, "too far from the model"),
        ("float frame id", j, json.dumps({"points": pts, "frame_id": 1.5}), 422, "frame_id"),
        ("body is a list", j, json.dumps([pts]), 422, "map"),
        ("invalid JSON", j, b'{"points": [[1, 2, 3]', 422, "not valid JSON"),
        ("garbage msgpack", MSGPACK, b"\xc1\xc1\xc1garbage", 422, "not valid MessagePack"),
        ("reserved byte", MSGPACK, b"\xc1", 422, "not valid MessagePack: a byte that starts no"),
        (
            "maps nested deep",
            MSGPACK,
            b"\x81\xa1a" * 5000 + b"\xc0",
            422,
            "not valid MessagePack: lists and maps nested",
        ),
        (
            "lists nested deep",
            MSGPACK,
            b"\x91" * 100_000 + b"\xc0",
            422,
            "not valid MessagePack: lists and maps nested",
        ),
        ("empty body", j, b"", 422, "required"),
        ("object dtype", MSGPACK, mp({"points": {"dtype": "|O", "shape": [1, 3], "data": b"\0" * 24}}), 422, "dtype"),
        ("big-endian", MSGPACK, mp({"points": {"dtype": ">f8", "shape": [1, 3], "data": b"\0" * 24}}), 422, "dtype"),
        (
            "short data",
            MSGPACK,
            mp({"points": {"dtype": "<f8", "shape": [2, 3], "data": b"\0" * 24}}),
            422,
            "needs 48 bytes",
        ),
        ("data as text", MSGPACK, mp({"points": {"dtype": "<f8", "shape": [1, 3], "data": "abc"}}), 422, "bin"),
        ("negative shape", MSGPACK, mp({"points": {"dtype": "<f8", "shape": [-1, 3], "data": b""}}), 422, "shape"),
        ("extension type", MSGPACK, b"\xd4\x05\x00", 422, "extension"),
        ("too many points", j, json.dumps({"points": np.zeros((MAX_POINTS + 1, 3)).tolist()}), 413, "limit"),
        ("too many packed points", MSGPACK, mp({"points": packed(np.zeros((MAX_POINTS + 1, 3)))}), 413, "limit"),
        ("body too large", j, b" " * (2 << 20), 413, "limit"),
        ("unsupported media", {"content-type": "text/xml"}, b"<points/>", 415, "Content-Type"),
    ]
    return cases


def test_every_frame_error_leaves_the_session_intact(http, entry, support, clouds):
    config = SessionConfig(support=tuple(support.tolist()), outputs=("displacement", "forces"))
    ref = Session(entry.network, config)
    sid = http.post("/sessions", json={"model": "bar", "support": support.tolist()}).json()["session"]
    cases = _bad_frames(entry, support)
    for k, (name, headers, body, status, words) in enumerate(cases):
        r = http.post(f"/sessions/{sid}/frames", content=body, headers=headers)
        assert r.status_code == status, (name, r.status_code, r.text[:300])
        detail = r.json()["detail"] if "json" in r.headers["content-type"] else None
        text = json.dumps(detail) if detail is not None else r.text
        assert words in text, (name, text[:300])
        if k % 4 == 0 or k == len(cases) - 1:  # the session still works, its state as if nothing happened
            pts = clouds[(k // 4) % len(clouds)]
            want = ref.frame(pts)
            got = http.post(f"/sessions/{sid}/frames", json={"points": pts.tolist()}).json()
            np.testing.assert_allclose(got["forces"], want.outputs["forces"], rtol=1e-9, atol=1e-12)
            assert got["iterations"] == want.iterations
    assert http.get(f"/sessions/{sid}").json()["counters"]["frames"] == ref.frames
    http.delete(f"/sessions/{sid}")


@pytest.mark.parametrize(
    "config, status, words",
    [
        ({"model": "nope"}, 404, "no model 'nope'"),
        ({}, 422, "Field required"),
        ({"model": "bar", "alpha": 0}, 422, "greater than 0"),
        ({"model": "bar", "alpha": -1e-3}, 422, "greater than 0"),
        ({"model": "bar", "gtol": 0}, 422, "greater than 0"),
        ({"model": "bar", "max_iter": 0}, 422, "greater than or equal to 1"),
        ({"model": "bar", "max_iter": 1001}, 422, "max_iter 1001 is over this server's cap of 1000"),
        ({"model": "bar", "max_iter": 10**9}, 422, "max_iter 1000000000 is over this server's cap of 1000"),
        ({"model": "bar", "max_iter": 5.0}, 422, "valid integer"),
        ({"model": "bar", "outputs": ["displacement", "velocity"]}, 422, "outputs"),
        ({"model": "bar", "outputs": ["forces", "forces"]}, 422, "repeat"),
        ({"model": "bar", "method": "magic"}, 422, "method"),
        ({"model": "bar", "E": -1}, 422, "greater than 0"),
        ({"model": "bar", "force_bound": 0}, 422, "greater than 0"),
        ({"model": "bar", "warm_start": "yes"}, 422, "valid boolean"),
        ({"model": "bar", "support": [0, 70]}, 422, "fixed"),
        ({"model": "bar", "support": [70, 99]}, 422, "0..80"),
        ({"model": "bar", "matching": [[1, 2, 500]]}, 422, "0..80"),
        ({"model": "bar", "matching": [[1, 2]]}, 422, "triples"),
        ({"model": "bar", "matching": [[1, 2, True]]}, 422, "not booleans"),
        ({"model": "bar", "matching": [[0, 0, 0]]}, 422, "matching face 0 [0, 0, 0] repeats a node"),
        ({"model": "bar", "matching": [[1, 2, 5], [7, 8, 7]]}, 422, "matching face 1 [7, 8, 7] repeats a node"),
        ({"model": "bar", "loss": "huber"}, 422, "huber"),
        ({"model": "bar", "loss": "trimmed", "loss_param": 1.5}, 422, "less than or equal to 1"),
        ({"model": "bar", "colour": "red"}, 422, "Extra inputs"),
    ],
)
def test_session_config_errors(http, config, status, words):
    before = http.get("/health").json()["sessions"]["open"]
    r = http.post("/sessions", json=config)
    assert r.status_code == status, r.text
    assert words in json.dumps(r.json()["detail"])
    assert http.get("/health").json()["sessions"]["open"] == before  # nothing left behind


@pytest.mark.parametrize(
    "field, value, words",
    [
        ("support", [0, 70], "fixed"),
        ("support", [70, 99], "0..80"),
        ("support", [70, 70], "repeats"),
        ("support", "interior", "region"),
        ("matching", [[1, 2, 500]], "0..80"),
    ],
)
def test_session_node_errors_name_their_field_as_a_frame_does(http, entry, support, field, value, words):
    if value == "interior":  # a free node the network cannot load
        value = np.setdiff1d(np.flatnonzero(entry.mesh.free_mask), entry.region)[:1].tolist()
    r = http.post("/sessions", json={"model": "bar", field: value})
    assert r.status_code == 422, r.text
    [error] = r.json()["detail"]
    assert error["loc"] == ["body", field] and words in error["msg"], error
    if field == "support":  # the same mistake in a frame: the same loc
        sid = http.post("/sessions", json={"model": "bar"}).json()["session"]
        frame = http.post(f"/sessions/{sid}/frames", json={"points": [[0.0, 0.0, 0.0]], "support": value})
        assert frame.json()["detail"][0]["loc"] == error["loc"], frame.text
        http.delete(f"/sessions/{sid}")


def test_a_matching_face_without_area_is_refused_naming_it(http, entry):
    """Three nodes on one line of the bar: a triangle without a normal, whose session opened and
    answered every frame non_finite with no estimate. A 422 naming the face, nothing opened."""
    x = entry.mesh.nodes
    line = np.flatnonzero((x[:, 1] == 0.0) & (x[:, 2] == 0.0))[:3].tolist()
    good = entry.mesh.surface_faces[:2].tolist()
    before = http.get("/health").json()["sessions"]["open"]
    r = http.post("/sessions", json={"model": "bar", "matching": [*good, line]})
    assert r.status_code == 422, r.text
    [error] = r.json()["detail"]
    assert error["loc"] == ["body", "matching"] and f"matching face 2 {line} has no area at rest" in error["msg"]
    assert http.get("/health").json()["sessions"]["open"] == before
    r = http.post("/sessions", json={"model": "bar", "matching": good})
    assert r.status_code == 201, r.text
    http.delete(f"/sessions/{r.json()['session']}")


def test_boolean_coordinates_are_refused_as_booleans(http):
    sid = http.post("/sessions", json={"model": "bar"}).json()["session"]
    r = http.post(f"/sessions/{sid}/frames", json={"points": [[True, False, True]]})
    assert r.status_code == 422 and "points must hold numbers, not booleans" in r.json()["detail"][0]["msg"], r.text
    http.delete(f"/sessions/{sid}")


def test_errors_in_msgpack_when_asked(http):
    from .conftest import unpack

    r = http.post("/sessions", content=mp({"model": "bar", "alpha": -1}), headers=MSGPACK)
    assert r.status_code == 422 and r.headers["content-type"] == "application/msgpack"
    assert unpack(r.content)["detail"][0]["loc"] == ["body", "alpha"]


def test_unknown_route_and_method(http):
    assert http.get("/nowhere").status_code == 404
    assert http.put("/sessions").status_code == 405


@pytest.mark.parametrize("query", ["seed=-1", "frames=1", "points=5", "seed=x"])
def test_the_viewers_demo_refuses_bad_queries_with_422(http, query):
    """A negative seed was a 500 that dropped the keep-alive connection (numpy refuses it); each
    bad query is a 422 that names it, and the connection serves the next request."""
    r = http.get(f"/models/bar/demo?{query}")
    assert r.status_code == 422 and query.split("=")[0] in r.text
    assert http.get("/health").status_code == 200

"""No body, valid or not, makes the server answer 500: schemathesis generates requests from
/openapi.json for every operation, and hypothesis throws arbitrary values, mutated frames and
garbage at the bodies and the WebSocket."""

from __future__ import annotations

import json

import httpx
import msgpack
import pytest
import schemathesis
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from websockets.sync.client import connect

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")  # extreme coordinates overflow inside the engine
FUZZ = settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)


@pytest.fixture(scope="module")
def api_schema(live):
    return schemathesis.openapi.from_url(live.url + "/openapi.json")


def test_no_operation_answers_500(api_schema, live):
    """Every operation of /openapi.json, with bodies, paths and queries drawn from its schema
    (schemathesis as a library: its pytest plugin does not run under this pytest)."""
    operations = [op.ok() for op in api_schema.get_all_operations()]
    assert len(operations) == 9
    for op in operations:

        @given(case=op.as_strategy())
        @FUZZ
        def check(case):
            if case.media_type and "msgpack" in case.media_type:  # the JSON form of the same schema
                case.media_type = "application/json"
            response = case.call(base_url=live.url, timeout=60)
            assert response.status_code < 500, (case.method, case.path, response.text[:500])
            assert response.status_code in {200, 201, 204, 404, 405, 409, 413, 415, 422, 503}

        check()


@pytest.fixture(scope="module")
def frames_op(api_schema):
    return api_schema["/sessions/{session_id}/frames"]["POST"]


@pytest.fixture(scope="module")
def session_id(live, support):
    with httpx.Client(base_url=live.url) as c:
        sid = c.post("/sessions", json={"model": "bar", "support": support.tolist(), "max_iter": 20}).json()["session"]
    yield sid
    with httpx.Client(base_url=live.url) as c:
        c.delete(f"/sessions/{sid}")


def test_schema_generated_frames_on_a_real_session(live, frames_op, session_id):
    """Frames generated from FrameIn's schema, posted to a session that exists."""

    @given(case=frames_op.as_strategy())
    @FUZZ
    def check(case):
        case.path_parameters = {"session_id": session_id}
        case.media_type = "application/json"
        response = case.call(base_url=live.url, timeout=60)
        assert response.status_code in {200, 413, 422}, response.text[:500]

    check()


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False, allow_infinity=False) | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=20,
)
node_ids = st.lists(st.one_of(st.integers(-5, 100), st.floats(-1, 100), st.booleans(), st.text(max_size=2)), max_size=6)
points = st.one_of(
    st.lists(st.lists(st.floats(-2, 5) | st.integers(-3, 3), min_size=0, max_size=4), max_size=6),
    json_values,
)
frames = st.fixed_dictionaries(
    {"points": points},
    optional={"support": node_ids | json_values, "frame_id": st.integers() | st.text(max_size=5) | json_values},
)
configs = st.fixed_dictionaries(
    {"model": st.sampled_from(["bar", "nope", ""]) | json_values},
    optional={
        "method": st.sampled_from(["network", "fem", "x"]),
        "support": node_ids,
        "alpha": st.floats(allow_nan=False) | json_values,
        "gtol": st.floats(-1, 2),
        "max_iter": st.integers(-2, 20_000) | st.floats(0, 5),
        "outputs": st.lists(
            st.sampled_from(["displacement", "surface_displacement", "forces", "stress", "x"]), max_size=5
        ),
        "loss": st.sampled_from(["squared", "huber", "trimmed", "l1"]),
        "loss_param": st.floats(-1, 2) | st.none(),
        "matching": st.lists(node_ids, max_size=3),
        "E": st.floats(-10, 1e5) | st.none(),
        "skip_stale": st.booleans() | json_values,
    },
)


def _packable(obj) -> bool:
    try:
        msgpack.packb(obj)
    except OverflowError:
        return False
    return True


def packb(obj) -> bytes:
    """MessagePack of obj; integers past 64 bits cannot be packed, so such a draw is discarded
    (JSON sends them, and the JSON draws test them)."""
    try:
        return msgpack.packb(obj)
    except OverflowError:
        assume(False)
        raise


@given(body=frames, binary=st.booleans())
@FUZZ
def test_arbitrary_frames_never_500(live, session_id, body, binary):
    with httpx.Client(base_url=live.url, timeout=60) as c:
        if binary:
            r = c.post(
                f"/sessions/{session_id}/frames",
                content=packb(body),
                headers={"content-type": "application/msgpack"},
            )
        else:
            r = c.post(f"/sessions/{session_id}/frames", json=body)
    assert r.status_code in {200, 413, 422}, r.text[:500]


@given(body=configs)
@FUZZ
def test_arbitrary_session_configs_never_500(live, body):
    with httpx.Client(base_url=live.url, timeout=60) as c:
        r = c.post("/sessions", json=body)
        assert r.status_code in {201, 404, 422, 503}, r.text[:500]
        if r.status_code == 201:
            c.delete(f"/sessions/{r.json()['session']}")


@given(
    body=st.fixed_dictionaries(
        {"forces": st.fixed_dictionaries({"nodes": node_ids, "values": points}) | json_values},
        optional={"method": st.sampled_from(["network", "fem", "?"]), "E": st.floats(-1, 1e4)},
    )
)
@FUZZ
def test_arbitrary_simulate_bodies_never_500(live, body):
    with httpx.Client(base_url=live.url, timeout=60) as c:
        r = c.post("/models/bar/simulate", json=body)
    assert r.status_code in {200, 422}, r.text[:500]


def test_websocket_garbage_and_arbitrary_frames(live, support, clouds):
    """One stream takes binary garbage, text garbage and arbitrary frames; each gets an answer
    (a result or an error message) and the stream stays open throughout."""
    with connect(live.ws) as ws:
        ws.send(json.dumps({"model": "bar", "support": support.tolist(), "max_iter": 10}))
        json.loads(ws.recv(timeout=30))

        @given(
            message=st.one_of(
                st.binary(max_size=64),
                st.text(max_size=64),
                frames.map(json.dumps),
                frames.filter(lambda f: _packable(f)).map(msgpack.packb),
            )
        )
        @FUZZ
        def check(message):
            ws.send(message)
            reply = ws.recv(timeout=60)
            obj = msgpack.unpackb(reply) if isinstance(reply, bytes) else json.loads(reply)
            assert "error" in obj or "converged" in obj
            if "error" in obj:
                assert obj["error"]["code"] in (413, 422), obj

        check()
        ws.send(json.dumps({"points": clouds[0].tolist(), "frame_id": "end"}))  # a cloud the bar's size
        assert json.loads(ws.recv(timeout=60))["frame_id"] == "end"

"""The codec: packed arrays both ways, strict decoding, negotiation, timed encoding."""

from __future__ import annotations

import json
import time

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.api import codec
from service.api.codec import JSON, MSGPACK, DecodeError, UnsupportedMedia


@pytest.fixture(params=["orjson", "stdlib"], autouse=True)
def json_backend(request, monkeypatch):
    """Every test runs with orjson (when installed) and with the standard library's json."""
    if request.param == "orjson":
        if codec.orjson is None:
            pytest.skip("orjson is not installed")
    else:
        monkeypatch.setattr(codec, "orjson", None)
    return request.param


@pytest.mark.parametrize("dtype", ["<f4", "<f8", "<i4", "<i8"])
def test_packed_round_trip(dtype):
    a = (np.arange(12).reshape(4, 3) * 1.5).astype(dtype)
    back = codec.decode(codec.encode({"a": a, "nested": {"b": a[0]}}, MSGPACK), MSGPACK)
    assert back["a"].dtype == np.dtype(dtype) and back["a"].shape == (4, 3)
    np.testing.assert_array_equal(back["a"], a)
    np.testing.assert_array_equal(back["nested"]["b"], a[0])


def test_json_lists_and_scalars():
    body = codec.encode(
        {
            "a": np.eye(2),
            "n": np.int64(3),
            "x": np.float32(0.5),
            "t": np.eye(3)[:, 0],
            "i": np.arange(3, dtype=np.int32),
            "h": np.ones(2, np.float16),
        },
        JSON,
    )
    assert json.loads(body) == {
        "a": [[1.0, 0.0], [0.0, 1.0]],
        "n": 3,
        "x": 0.5,
        "t": [1.0, 0.0, 0.0],
        "i": [0, 1, 2],
        "h": [1.0, 1.0],
    }


@pytest.mark.parametrize("number", [b"1e999", b"-1e999", b"%d" % 10**400, b"-%d" % 10**400])
def test_json_numbers_past_a_doubles_range_are_refused_as_out_of_range(number):
    """1e999 and an integer of 400 digits were refused by orjson as "NaN and Infinity", or read
    as inf (the standard library) for a validator to call NaN: both say out of range. A number
    just inside the range is read."""
    with pytest.raises(DecodeError, match="a JSON number is out of range: its magnitude is past 1.798e[+]308"):
        codec.decode(b'{"a": [0, %s]}' % number, JSON)
    assert float(codec.decode(b'{"a": %d}' % 10**308, JSON)["a"]) == 1e308  # orjson reads a double


def test_non_finite_become_null_in_json_and_stay_in_msgpack():
    body = {"u": np.array([1.0, np.nan, np.inf]), "J": float("inf")}
    assert json.loads(codec.encode(body, JSON)) == {"u": [1.0, None, None], "J": None}
    back = codec.decode(codec.encode(body, MSGPACK), MSGPACK)
    assert np.isnan(back["u"][1]) and back["J"] == float("inf")


@pytest.mark.parametrize(
    "packed, words",
    [
        ({"dtype": "|O", "shape": [1], "data": b"\0" * 8}, "dtype"),
        ({"dtype": "<f2", "shape": [1], "data": b"\0" * 2}, "dtype"),
        ({"dtype": ">f8", "shape": [1], "data": b"\0" * 8}, "dtype"),
        ({"dtype": "<f8", "shape": [2], "data": b"\0" * 8}, "needs 16 bytes"),
        ({"dtype": "<f8", "shape": [1], "data": "text"}, "bin"),
        ({"dtype": "<f8", "shape": [-1], "data": b""}, "shape"),
        ({"dtype": "<f8", "shape": [1.0], "data": b"\0" * 8}, "shape"),
        ({"dtype": "<f8", "shape": [], "data": b"\0" * 8}, "shape"),
        ({"dtype": "<f8", "shape": [1, 1, 1, 1, 1], "data": b"\0" * 8}, "shape"),
        ({"dtype": "<f8", "shape": 3, "data": b"\0" * 24}, "shape"),
    ],
)
def test_bad_packed_arrays(packed, words):
    with pytest.raises(DecodeError, match=words.replace("(", r"\(")):
        codec.decode(msgpack.packb({"points": packed}, use_bin_type=True), MSGPACK)


@pytest.mark.parametrize(
    "data, kind, words",
    [
        (b'{"a": NaN}', JSON, "NaN"),
        (b'{"a": -Infinity}', JSON, "NaN"),
        ('{"a": [1, Infinity]}', JSON, "NaN"),
        (b'{"a": ', JSON, "not valid JSON"),
        (b'{"frame_id": "NaN-camera", "points": [1,', JSON, "not valid JSON"),  # NaN in a string, cut short
        ('{"frame_id": "\u00e9t\u00e9", "a": NaN}', JSON, "NaN"),  # where it failed, counted in characters
        (b"\xff\xfe\x00", JSON, "not valid JSON"),
        (b"[" * 100_000, JSON, "lists and maps"),  # refused before parsing (TooLarge, a DecodeError)
        (b"\xc1", MSGPACK, "not valid MessagePack: a byte that starts no MessagePack value"),  # msgpack says nothing
        (b"\x81\xa1a" * 5000 + b"\xc0", MSGPACK, "not valid MessagePack: lists and maps nested too deep"),
        (b"\x91" * 100_000 + b"\xc0", MSGPACK, "not valid MessagePack: lists and maps nested too deep"),
        (msgpack.packb({"a": 1}) + b"\x00", MSGPACK, "extra data"),
        (msgpack.packb({1: 2}), MSGPACK, "map key"),
        (msgpack.packb(msgpack.ExtType(7, b"x")), MSGPACK, "extension"),
        (b"\x91" * 100_000, MSGPACK, "not valid MessagePack"),
        ("text", MSGPACK, "binary"),
        (b"x" * (2 << 20), JSON, "over the limit"),
    ],
)
def test_strict_decoding(data, kind, words):
    with pytest.raises(DecodeError, match=words):
        codec.decode(data, kind, max_bytes=1 << 20)


@given(st.binary(max_size=200))
@settings(max_examples=300, deadline=None)
def test_garbage_never_escapes_as_anything_but_decode_error(data):
    for kind in (JSON, MSGPACK):
        try:
            codec.decode(data, kind)
        except DecodeError:
            pass


@pytest.mark.parametrize(
    "accept, content_type, kind",
    [
        (None, None, JSON),
        (None, "application/msgpack", MSGPACK),
        ("application/json", "application/msgpack", JSON),  # Accept wins
        ("application/msgpack", "application/json", MSGPACK),
        ("application/x-msgpack", None, MSGPACK),
        ("*/*", "application/msgpack", MSGPACK),  # no preference: the request's encoding
        ("application/json;q=0.5, application/msgpack", None, MSGPACK),
        ("application/json, application/msgpack;q=0.1", None, JSON),
        ("text/html", "application/msgpack; charset=x", MSGPACK),
    ],
)
def test_negotiation(accept, content_type, kind):
    assert codec.response_kind(accept, content_type) == kind


def test_unsupported_content_type():
    with pytest.raises(UnsupportedMedia):
        codec.request_kind("application/xml")
    assert codec.request_kind("application/problem+json") == JSON
    for media in ("text/plain+json", "image/svg+json"):  # JSON's suffix under application/ only
        with pytest.raises(UnsupportedMedia):
            codec.request_kind(media)


@pytest.mark.parametrize("kind", [JSON, MSGPACK])
def test_encode_timed_appends_its_own_time(kind):
    timing = {"total": 1.0}
    t0 = time.perf_counter()
    body = codec.encode_timed({"u": np.ones((1000, 3)), "ok": True}, kind, timing)
    call_ms = 1e3 * (time.perf_counter() - t0)
    back = codec.decode(body, kind)
    assert back["ok"] is True and set(back["timing_ms"]) == {"total", "encode"} and back["timing_ms"]["total"] == 1.0
    # the figure is the encoding's own time: measured (not zero), and within the call that made it
    assert np.asarray(back["u"]).shape == (1000, 3) and 0 < back["timing_ms"]["encode"] <= call_ms
    assert back["timing_ms"]["encode"] == timing["encode"]
    empty = codec.decode(codec.encode_timed({}, kind, {}), kind)
    assert set(empty) == {"timing_ms"} and set(empty["timing_ms"]) == {"encode"} and empty["timing_ms"]["encode"] > 0

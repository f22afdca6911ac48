"""Bodies on the wire: JSON or MessagePack, NumPy arrays packed (MessagePack) or listed (JSON)
on the way out and NumPy arrays again on the way in."""

from __future__ import annotations

import json
import math

import msgpack
import numpy as np

try:  # optional: faster JSON that writes NumPy arrays itself
    import orjson
except ImportError:  # pragma: no cover
    orjson = None

JSON_MEDIA = "application/json"
MSGPACK_MEDIA = "application/msgpack"
_FLOAT_KEYS = frozenset(
    {"displacement", "surface_displacement", "forces", "stress", "net_force", "nodes", "values", "points"}
)
_INT_KEYS = frozenset({"support", "tets", "surface_faces", "surface_nodes", "fixed_nodes", "region_nodes", "matching"})
_PACKED = frozenset({"dtype", "shape", "data"})
_DTYPES = {"<f4", "<f8", "<i4", "<i8"}


def _pack(a: np.ndarray) -> dict:
    if a.dtype.kind == "f":
        dt = "<f4" if a.dtype.itemsize == 4 else "<f8"
    elif a.dtype.kind in "iu":
        dt = "<i4" if a.dtype.kind == "i" and a.dtype.itemsize <= 4 else "<i8"
    else:
        raise TypeError(f"cannot send an array of dtype {a.dtype}")
    a = np.ascontiguousarray(a, dtype=dt)
    return {"dtype": dt, "shape": list(a.shape), "data": a.tobytes()}


def _outgoing(obj, encoding: str):
    if isinstance(obj, np.ndarray):
        if encoding == "msgpack":
            return _pack(obj)
        return obj if orjson is not None else obj.tolist()
    if isinstance(obj, dict):
        return {k: _outgoing(v, encoding) for k, v in obj.items() if v is not None}
    if isinstance(obj, (list, tuple)):
        return [_outgoing(v, encoding) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def encode(obj, encoding: str) -> bytes:
    """A request body (arrays packed for MessagePack, listed for JSON; None values left out)."""
    obj = _outgoing(obj, encoding)
    if encoding == "msgpack":
        return msgpack.packb(obj, use_bin_type=True)
    if orjson is not None and _finite(obj):
        return orjson.dumps(obj, default=_tolist, option=orjson.OPT_SERIALIZE_NUMPY)
    # NaN and Infinity written as such (orjson writes null, which read "numbers only"): the
    # server's 422 then names them, as it does a MessagePack body's
    return json.dumps(obj, separators=(",", ":"), default=_tolist).encode()


def _finite(obj) -> bool:
    """Whether a body (arrays still arrays: orjson's) holds no NaN or infinity."""
    if isinstance(obj, np.ndarray):
        return obj.dtype.kind != "f" or bool(np.isfinite(obj).all())
    if isinstance(obj, float):
        return math.isfinite(obj)
    if isinstance(obj, dict):
        return all(_finite(v) for v in obj.values())
    if isinstance(obj, list):
        return all(_finite(v) for v in obj)
    return True


def _tolist(obj):
    if isinstance(obj, (np.ndarray, np.generic)):
        return obj.tolist()
    raise TypeError(f"cannot encode {type(obj).__name__} as JSON")


def _incoming(obj, key: str | None = None):
    if isinstance(obj, dict):
        if obj.keys() == _PACKED and obj.get("dtype") in _DTYPES:
            return np.frombuffer(obj["data"], dtype=obj["dtype"]).reshape(obj["shape"]).copy()
        return {k: _incoming(v, k) for k, v in obj.items()}
    if isinstance(obj, list):
        if key in _FLOAT_KEYS:
            return np.asarray(obj, dtype=np.float64)  # JSON null (a non-finite value) -> NaN
        if key in _INT_KEYS:
            return np.asarray(obj, dtype=np.int64)
        return [_incoming(v) for v in obj]
    return obj


def decode(data: bytes | str, encoding: str):
    """A reply body, arrays as NumPy arrays (packed ones copied: writable)."""
    if encoding == "msgpack":
        obj = msgpack.unpackb(data, raw=False)
    else:
        obj = orjson.loads(data) if orjson is not None else json.loads(data)
    return _incoming(obj)

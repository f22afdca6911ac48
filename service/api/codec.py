"""Bodies in and out: JSON or MessagePack, arrays as nested lists or packed bytes.

A packed array (MessagePack only) is a map ``{"dtype": "<f8", "shape": [m, 3], "data": <bin>}``:
little-endian, C order, one of four dtypes. Requests may use it wherever an array goes (as the
value of a map key); MessagePack responses always do. JSON responses carry nested lists.

Decoding is strict: no pickle or extension types, sizes bounded, JSON's ``NaN``/``Infinity``
literals refused and its numbers past a double's range too ("out of range"), packed arrays
checked against their declared shape before they are viewed (``np.frombuffer``, no copy, no
per-element Python). Its cost is bounded by a small multiple of
the body: an empty list is one byte of MessagePack and 64 bytes of Python, so the containers a
body may hold are bounded by its size (one per ``_BYTES_PER_CONTAINER`` bytes, beyond a few
thousand) and its array elements by ``max_elements``; JSON is counted before it is parsed (a
scan of its bytes), MessagePack as it is built, refused at the first container over a
bound. JSON goes through orjson when it is installed (arrays written from NumPy directly), else
the standard library; both give the same bodies and refuse the same inputs.

>>> body = encode({"points": np.zeros((2, 3))}, MSGPACK)
>>> decode(body, MSGPACK)["points"].shape
(2, 3)
>>> decode(b'{"x": NaN}', JSON)
Traceback (most recent call last):
...
service.api.codec.DecodeError: NaN and Infinity are not valid JSON numbers
"""

from __future__ import annotations

import json
import math
import re
import sys
import time

import msgpack
import numpy as np

try:  # optional: a C JSON codec that writes NumPy arrays itself (5-20x faster than json + tolist)
    import orjson
except ImportError:  # pragma: no cover - the stdlib path is the reference
    orjson = None

JSON = "json"
MSGPACK = "msgpack"
MEDIA = {JSON: "application/json", MSGPACK: "application/msgpack"}
_MSGPACK_TYPES = {"application/msgpack", "application/x-msgpack", "application/vnd.msgpack"}
DTYPES = {"<f4": np.dtype("<f4"), "<f8": np.dtype("<f8"), "<i4": np.dtype("<i4"), "<i8": np.dtype("<i8")}
_PACKED_KEYS = frozenset(("dtype", "shape", "data"))
MAX_DIMS = 4
MAX_DEPTH = 32


class DecodeError(ValueError):
    """A body that is not valid JSON / MessagePack, or a malformed packed array."""


class UnsupportedMedia(ValueError):
    """A Content-Type the service does not speak (HTTP 415)."""


class TooLarge(DecodeError):
    """A body whose decoding would cost more than its limits allow (HTTP 413)."""


#: legitimate bodies hold one container (list or map) per 7 bytes or more (``[1,2,3],`` is the
#: densest: a mesh's matching triangles as JSON); an empty list is 1-2 bytes of input and 64 of
#: Python. Allowing one per 6 bytes keeps decoding within ~20x the body's size.
_BYTES_PER_CONTAINER = 6
_FREE_CONTAINERS = 4096  # small bodies are never refused for their shape


# -- negotiation ---------------------------------------------------------------------------------


def _media(value: str) -> str:
    return value.split(";", 1)[0].strip().lower()


def _is_json(media: str) -> bool:
    """application/json, or an application type with JSON's structured suffix (RFC 6839)."""
    return media == "application/json" or (media.startswith("application/") and media.endswith("+json"))


def request_kind(content_type: str | None) -> str:
    """The encoding of a request body from its Content-Type: JSON or MessagePack types only. A
    web page can send ``text/plain``, a form or no type at all without a CORS preflight (so
    without the server's consent), never these."""
    media = _media(content_type or "")
    if media in _MSGPACK_TYPES:
        return MSGPACK
    if _is_json(media):
        return JSON
    raise UnsupportedMedia(
        f"unsupported Content-Type {media or '(none)'!r}: use application/json or application/msgpack"
    )


def response_kind(accept: str | None, content_type: str | None) -> str:
    """The encoding of a reply: ``Accept`` wins when it names one of ours, else the request's."""
    best, best_q = None, 0.0
    for part in (accept or "").split(","):
        fields = part.split(";")
        media = fields[0].strip().lower()
        q = 1.0
        for f in fields[1:]:
            name, _, value = f.partition("=")
            if name.strip() == "q":
                try:
                    q = float(value)
                except ValueError:
                    q = 0.0
        if media in _MSGPACK_TYPES:
            kind = MSGPACK
        elif _is_json(media):
            kind = JSON
        else:
            kind = None
        if kind and q > best_q:
            best, best_q = kind, q
    if best is not None:
        return best
    try:
        return request_kind(content_type)
    except UnsupportedMedia:
        return JSON


# -- arrays --------------------------------------------------------------------------------------


def pack_array(a: np.ndarray) -> dict:
    """The packed form of an array (float -> <f8 or <f4 as it is, integers -> <i8 or <i4)."""
    a = np.asarray(a)
    if a.dtype.kind == "f":
        dt = "<f4" if a.dtype.itemsize == 4 else "<f8"
    elif a.dtype.kind in "iu" or a.dtype.kind == "b":
        dt = "<i4" if a.dtype.itemsize <= 4 and a.dtype.kind == "i" else "<i8"
    else:
        raise TypeError(f"cannot pack an array of dtype {a.dtype}")
    a = np.ascontiguousarray(a, dtype=DTYPES[dt])
    return {"dtype": dt, "shape": list(a.shape), "data": a.tobytes()}


def unpack_array(d: dict) -> np.ndarray:
    """The array a packed map describes (read-only view of its bytes). Raises DecodeError."""
    dtype, shape, data = d.get("dtype"), d.get("shape"), d.get("data")
    if dtype not in DTYPES:
        raise DecodeError(f"packed array dtype must be one of {sorted(DTYPES)}, got {dtype!r}")
    if not isinstance(data, (bytes, bytearray)):
        raise DecodeError("packed array data must be MessagePack bin (bytes)")
    if (
        not isinstance(shape, list)
        or not 1 <= len(shape) <= MAX_DIMS
        or not all(type(s) is int and 0 <= s for s in shape)
    ):
        raise DecodeError(f"packed array shape must be a list of 1 to {MAX_DIMS} non-negative integers, got {shape!r}")
    dt = DTYPES[dtype]
    need = math.prod(shape) * dt.itemsize
    if need != len(data):
        raise DecodeError(f"packed array of shape {shape} and dtype {dtype} needs {need} bytes, got {len(data)}")
    return np.frombuffer(data, dtype=dt).reshape(shape)


def _unpack_tree(obj, depth: int = 0):
    """Packed arrays (as map values, or the whole body) replaced by arrays; lists not walked."""
    if depth > MAX_DEPTH:
        raise DecodeError(f"nesting deeper than {MAX_DEPTH}")
    if isinstance(obj, dict):
        if obj.keys() == _PACKED_KEYS:
            return unpack_array(obj)
        for k, v in obj.items():
            if isinstance(v, dict):
                obj[k] = _unpack_tree(v, depth + 1)
    return obj


# -- decode --------------------------------------------------------------------------------------


def _no_constants(name: str):
    raise DecodeError("NaN and Infinity are not valid JSON numbers")


def _no_ext(code: int, data: bytes):
    raise DecodeError(f"MessagePack extension types are not accepted (got ext type {code})")


_NON_FINITE = re.compile(r"NaN|Infinity")


#: orjson's words for a number past a double's range (1e999, or an integer of 309 digits or more)
_ORJSON_RANGE = "number is infinity when parsed as double"


def _out_of_range(where: str) -> DecodeError:
    return DecodeError(f"a JSON number is out of range: its magnitude is past {sys.float_info.max:.4g} ({where})")


def _finite_float(text: str) -> float:
    """The standard library's float, refused past a double's range (it reads 1e999 as inf)."""
    value = float(text)
    if math.isinf(value):
        raise _out_of_range(text[:20])
    return value


def _ranged_int(text: str) -> int:
    """The standard library's integer, refused past a double's range, as orjson refuses it."""
    value = int(text)
    if len(text) > 300 and abs(value) > sys.float_info.max:  # exact: an int compares to a float exactly
        raise _out_of_range(f"an integer of {len(text.lstrip('-'))} digits")
    return value


def _loads_json(data: bytes | str):
    if orjson is not None:
        try:
            return orjson.loads(data)
        except orjson.JSONDecodeError as exc:
            text = data if isinstance(data, str) else bytes(data).decode("utf-8", "replace")
            if _ORJSON_RANGE in str(exc):  # 1e999, or 10**400 (orjson reads big integers as doubles)
                raise _out_of_range(f"char {exc.pos}") from None
            if _NON_FINITE.match(text, exc.pos):  # a literal where it failed
                raise DecodeError("NaN and Infinity are not valid JSON numbers") from None
            raise DecodeError(f"not valid JSON: {exc}") from None
    try:
        # numbers past a double's range refused, as orjson refuses them (a call per number: the
        # fallback's cost, where orjson is not installed)
        return json.loads(data, parse_constant=_no_constants, parse_float=_finite_float, parse_int=_ranged_int)
    except DecodeError:
        raise
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:
        raise DecodeError(f"not valid JSON: {exc}") from None


class _Budget:
    """What a body may still build: array elements (and map entries) and containers."""

    def __init__(self, size: int, max_elements: int) -> None:
        self.max_elements = max_elements
        self.max_containers = size // _BYTES_PER_CONTAINER + _FREE_CONTAINERS
        self.elements = 0
        self.containers = 0

    def check(self, elements: int, containers: int) -> None:
        if elements > self.max_elements:
            raise TooLarge(f"the body holds more than this server's limit of {self.max_elements} array elements")
        if containers > self.max_containers:
            raise TooLarge(
                f"the body holds more than {self.max_containers} lists and maps for its size: send large "
                "arrays packed, or as flat lists"
            )

    def list_hook(self, items: list) -> list:
        self.elements += len(items)
        self.containers += 1
        self.check(self.elements, self.containers)
        return items

    def object_hook(self, entries: dict) -> dict:
        self.elements += len(entries)
        self.containers += 1
        self.check(self.elements, self.containers)
        return entries


def _json_budget(data: bytes | str, max_elements: int) -> None:
    """Refuse a JSON body before parsing it when it may hold too much: each value after an
    array's or object's first follows a comma, so commas plus containers bound the elements
    (strings that hold these characters only make the bound looser, never too tight)."""
    raw = data.encode() if isinstance(data, str) else data
    containers = raw.count(b"[") + raw.count(b"{")
    _Budget(len(raw), max_elements).check(raw.count(b",") + containers, containers)


#: msgpack's errors that carry no message (its C unpacker raises them bare), in words
_MSGPACK_WORDS = {
    msgpack.FormatError: "a byte that starts no MessagePack value (0xc1 is reserved)",
    msgpack.StackError: "lists and maps nested too deep",
    RecursionError: "lists and maps nested too deep",
}


def _msgpack_why(exc: Exception) -> str:
    """What is wrong with a MessagePack body: msgpack's message, else its error's kind in words
    (a detail that ends at "not valid MessagePack: " says nothing)."""
    if str(exc):
        return str(exc)
    for kind, words in _MSGPACK_WORDS.items():
        if isinstance(exc, kind):
            return words
    return re.sub(r"(?<=[a-z])(?=[A-Z])", " ", type(exc).__name__).lower()  # ExtraData -> extra data


def decode(data: bytes | str, kind: str, *, max_bytes: int = 64 << 20, max_elements: int = 1 << 24):
    """Parse a body. Raises DecodeError for anything malformed, never a crash; TooLarge for a
    body over ``max_bytes``, or whose decoding would build more than ``max_elements`` array
    elements or more lists and maps than its size allows."""
    if len(data) > max_bytes:
        raise TooLarge(f"body of {len(data)} bytes is over the limit of {max_bytes}")
    if kind == JSON:
        _json_budget(data, max_elements)
        return _loads_json(data)
    if kind == MSGPACK:
        if isinstance(data, str):
            raise DecodeError("MessagePack bodies are binary")
        budget = _Budget(len(data), max_elements)
        # empty lists and maps (one byte each, 64 of Python) refused before anything is built;
        # other bytes of those values (in floats, packed data) are far rarer than one in eight
        empties = data.count(b"\x90") + data.count(b"\x80")
        if empties > len(data) // 8 + _FREE_CONTAINERS:
            raise TooLarge(f"the body holds {empties} empty lists and maps: more than its size allows")
        # a declared length is allocated before its items are read: no more than the body could hold
        most = min(len(data), max_elements)
        try:
            obj = msgpack.unpackb(
                data,
                raw=False,
                strict_map_key=True,
                use_list=True,
                ext_hook=_no_ext,
                list_hook=budget.list_hook,
                object_hook=budget.object_hook,
                max_bin_len=len(data),
                max_str_len=len(data),
                max_array_len=most,
                max_map_len=most // 2,
                max_ext_len=len(data),
            )
        except DecodeError:
            raise
        except ValueError as exc:
            if "exceeds max_" in str(exc):  # a declared length over the limits, refused before allocating
                raise TooLarge(
                    f"the body declares an array or map beyond its own size or this server's limit of "
                    f"{max_elements} array elements ({exc})"
                ) from None
            raise DecodeError(f"not valid MessagePack: {_msgpack_why(exc)}") from None
        except RecursionError as exc:
            raise DecodeError(f"not valid MessagePack: {_msgpack_why(exc)}") from None
        return _unpack_tree(obj)
    raise ValueError(f"unknown encoding {kind!r}")


# -- encode --------------------------------------------------------------------------------------


def _json_array(a: np.ndarray):
    if a.dtype.kind == "f" and not np.isfinite(a).all():  # JSON has no NaN: null instead
        o = a.astype(object)
        o[~np.isfinite(a)] = None
        return o.tolist()
    return a.tolist()


def _plain(obj, kind: str):
    """Arrays into the encoding's form; numpy scalars into Python ones; non-finite floats into
    null for JSON."""
    if isinstance(obj, np.ndarray):
        return pack_array(obj) if kind == MSGPACK else _json_array(obj)
    if isinstance(obj, dict):
        return {k: _plain(v, kind) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v, kind) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if kind == JSON and isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _dumps(obj, kind: str) -> bytes:
    if kind == MSGPACK:
        return msgpack.packb(obj, use_bin_type=True)
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def _orjson_default(obj):
    """What orjson does not write itself: odd arrays (non-contiguous, other dtypes), scalars."""
    if isinstance(obj, (np.ndarray, np.generic)):
        return _plain(obj, JSON)
    raise TypeError(f"cannot encode {type(obj).__name__} as JSON")


def _encode(obj, kind: str) -> bytes:
    if kind == JSON and orjson is not None:  # non-finite floats become null, as in _plain
        return orjson.dumps(obj, default=_orjson_default, option=orjson.OPT_SERIALIZE_NUMPY)
    return _dumps(_plain(obj, kind), kind)


def encode(obj, kind: str) -> bytes:
    """A reply body."""
    return _encode(obj, kind)


def encode_timed(obj: dict, kind: str, timing: dict) -> bytes:
    """Encode a map, then append ``timing_ms`` to it with the encoding's own time as
    ``timing["encode"]``: the reported figure covers the real encoding of everything else."""
    t0 = time.perf_counter()
    if kind == MSGPACK:
        packer = msgpack.Packer(use_bin_type=True)
        body = [packer.pack_map_header(len(obj) + 1)]
        for k, v in obj.items():
            body.append(packer.pack(k))
            body.append(packer.pack(_plain(v, kind)))
        timing["encode"] = 1e3 * (time.perf_counter() - t0)
        body.append(packer.pack("timing_ms"))
        body.append(packer.pack(_plain(timing, kind)))
        return b"".join(body)
    head = _encode(obj, kind)
    timing["encode"] = 1e3 * (time.perf_counter() - t0)
    tail = _encode(timing, kind)
    if head == b"{}":
        return b'{"timing_ms":' + tail + b"}"
    return head[:-1] + b',"timing_ms":' + tail + b"}"

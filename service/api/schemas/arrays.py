"""The arrays a body holds, as annotated NumPy types: one ``np.asarray`` per array, checked for
shape, dtype and finiteness (a one-line error naming the array), never an element at a time."""

from __future__ import annotations

import itertools
from typing import Annotated, Any

import numpy as np
from pydantic import Field, PlainValidator, WithJsonSchema

INT64 = 2**63 - 1


class TooManyPoints(ValueError):
    """A cloud over the configured limit (HTTP 413, not 422: the body is valid, just too big)."""


# -- arrays --------------------------------------------------------------------------------------


def _array(v: Any, what: str) -> np.ndarray:
    """One np.asarray: numbers only (no strings, booleans, None, ragged lists, objects)."""
    if isinstance(v, np.ndarray):
        a = v
    elif isinstance(v, list):
        try:
            a = np.asarray(v)
        except (ValueError, TypeError, OverflowError):
            raise ValueError(f"{what} must be a regular array of numbers (not ragged, no nulls)") from None
    else:
        raise ValueError(f"{what} must be an array (nested lists, or a packed array in MessagePack)")
    if a.dtype.kind not in "iuf":
        raise ValueError(
            f"{what} must hold numbers, not booleans" if a.dtype.kind == "b" else f"{what} must hold numbers only"
        )
    if not a.flags.writeable:  # a packed array views the message's bytes: the engine gets its own
        a = a.copy()
    return a


def _vectors(v: Any, what: str, *, empty: bool = False) -> np.ndarray:
    a = _array(v, what)
    if a.ndim != 2 or a.shape[1] != 3 or (a.shape[0] == 0 and not empty):
        raise ValueError(f"{what} must be a non-empty (m, 3) array, got shape {list(a.shape)}")
    # NumPy reads true among numbers as 1.0: the elements' types, scanned in C (7 ms at 100k
    # points, half an np.asarray); packed arrays have no boolean dtype (codec.DTYPES)
    if isinstance(v, list) and bool in set(map(type, itertools.chain.from_iterable(v))):
        raise ValueError(f"{what} must hold numbers, not booleans")
    a = a.astype(np.float64, copy=False)
    if not np.isfinite(a).all():
        raise ValueError(f"{what} contain NaN or infinite values")
    return a


def _points(v: Any) -> np.ndarray:
    return _vectors(v, "points")


def _force_values(v: Any) -> np.ndarray:
    return _vectors(v, "force values")


def _no_booleans(v: Any, what: str, depth: int) -> None:
    """JSON true and false are no node ids: NumPy would read a list mixing them with numbers
    as 1 and 0 (nested lists: `depth` levels)."""
    rows = [v] if depth == 1 else v
    if isinstance(v, list) and any(isinstance(x, bool) for row in rows if isinstance(row, list) for x in row):
        raise ValueError(f"{what} must be integers, not booleans")


def _node_ids(v: Any) -> np.ndarray:
    _no_booleans(v, "node ids", 1)
    a = _array(v, "node ids")
    if a.ndim != 1 or a.size == 0:
        raise ValueError(f"node ids must be a non-empty flat list, got shape {list(a.shape)}")
    return _ids(a, "node ids")


def _triangles(v: Any) -> np.ndarray:
    _no_booleans(v, "matching node ids", 2)
    a = _array(v, "matching")
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] == 0:
        raise ValueError(f"matching must be a non-empty list of node-id triples, got shape {list(a.shape)}")
    return _ids(a, "matching node ids")


def _ids(a: np.ndarray, what: str) -> np.ndarray:
    """A non-empty array of `what` as int64: integers, non-negative, within int64."""
    if a.dtype.kind == "f":
        raise ValueError(f"{what} must be integers")
    if a.dtype.kind == "u" and a.max() > INT64:
        raise ValueError(f"{what} must be non-negative integers below 2**63")
    a = a.astype(np.int64, copy=False)
    if a.min() < 0:
        raise ValueError(f"{what} must be non-negative integers")
    return a


_VEC3 = {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}
Points = Annotated[
    np.ndarray,
    PlainValidator(_points),
    WithJsonSchema({"type": "array", "items": _VEC3, "minItems": 1, "description": "(m, 3) finite coordinates"}),
]
ForceValues = Annotated[
    np.ndarray,
    PlainValidator(_force_values),
    WithJsonSchema({"type": "array", "items": _VEC3, "minItems": 1, "description": "(k, 3) newtons"}),
]
NodeIds = Annotated[
    np.ndarray,
    PlainValidator(_node_ids),
    WithJsonSchema({"type": "array", "items": {"type": "integer", "minimum": 0}, "minItems": 1}),
]
Triangles = Annotated[
    np.ndarray,
    PlainValidator(_triangles),
    WithJsonSchema(
        {
            "type": "array",
            "items": {"type": "array", "items": {"type": "integer", "minimum": 0}, "minItems": 3, "maxItems": 3},
            "minItems": 1,
        }
    ),
]
FrameId = Annotated[int, Field(ge=-INT64 - 1, le=INT64)] | Annotated[str, Field(max_length=256)]
Finite = Annotated[float, Field(allow_inf_nan=False)]


Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Tri = Annotated[list[int], Field(min_length=3, max_length=3)]

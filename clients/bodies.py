"""What the client's requests carry, shared by HTTP and WebSocket: a frame, a session's config,
a simulation's forces; node ids checked here, before anything is sent."""

from __future__ import annotations

import numpy as np


def _node_ids(ids, what: str) -> np.ndarray:
    """Node ids as int64, refused here if they are not integers: a cast would truncate 1.5 to 1
    and register over another node than the one meant (the server refuses them too). An empty
    list goes as it is: the server's 422 says why it is refused."""
    a = np.asarray(ids)
    if a.size == 0:  # [] is float64 to numpy: no ids, which the server refuses (422) as API.md says
        return a.astype(np.int64)
    if a.dtype.kind not in "iu":
        raise ValueError(f"{what} must be integer node ids, got dtype {a.dtype}")
    if _holds_bool(ids):
        raise ValueError(f"{what} must be integer node ids, got a bool among them (True is not node 1)")
    if a.dtype.kind == "u" and a.max() > np.iinfo(np.int64).max:  # the cast would wrap 2**64-1 to -1
        raise ValueError(f"{what}: node id {a.max()} is too large")
    return a.astype(np.int64, copy=False)


def _holds_bool(ids) -> bool:
    """Whether ids given as a list hold a bool, which numpy reads as an int among ints ([True, 2]
    is [1, 2]); an array's dtype already says (a bool array is refused by its kind)."""
    if isinstance(ids, np.ndarray):
        return False
    kinds = set(map(type, np.asarray(ids, dtype=object).ravel()))  # iterated in C, not in Python
    return not kinds.isdisjoint({bool, np.bool_})


def _real(value, what: str):
    """A number sent as it is (E, alpha, a config's other numbers), refused here if complex:
    the encoder cannot write one, and its imaginary part means nothing to the server."""
    if isinstance(value, (complex, np.complexfloating)):
        raise ValueError(f"{what} must be a real number, got {value!r}")
    return value


def _reals(values, what: str) -> np.ndarray:
    """Coordinates or forces as float64, refused here if complex (a cast would drop the
    imaginary part) or bool (True is no coordinate; the server refuses JSON's true too)."""
    a = np.asarray(values)
    if a.dtype.kind in "cb":
        raise ValueError(f"{what} must be real numbers, got dtype {a.dtype}")
    return a.astype(np.float64, copy=False)


def frame_body(points, support, frame_id) -> dict:
    return {
        "points": _reals(points, "points"),
        "support": None if support is None else _node_ids(support, "support"),
        "frame_id": frame_id,
    }


def config_body(model: str, config: dict) -> dict:
    body = {"model": model, **{key: _real(value, key) for key, value in config.items()}}
    for key in ("support", "matching"):
        if body.get(key) is not None:
            body[key] = _node_ids(body[key], key)
    if isinstance(body.get("outputs"), str):  # one output's name, not its letters
        body["outputs"] = [body["outputs"]]
    elif body.get("outputs") is not None:
        body["outputs"] = list(body["outputs"])
    return body


def simulate_body(nodes, values, method: str, E: float | None) -> dict:
    return {
        "forces": {"nodes": _node_ids(nodes, "forces' nodes"), "values": _reals(values, "force values")},
        "method": method,
        "E": _real(E, "E"),
    }

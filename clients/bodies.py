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
    return a.astype(np.int64, copy=False)


def frame_body(points, support, frame_id) -> dict:
    return {
        "points": np.asarray(points, dtype=np.float64),
        "support": None if support is None else _node_ids(support, "support"),
        "frame_id": frame_id,
    }


def config_body(model: str, config: dict) -> dict:
    body = {"model": model, **config}
    for key in ("support", "matching"):
        if body.get(key) is not None:
            body[key] = _node_ids(body[key], key)
    if body.get("outputs") is not None:
        body["outputs"] = list(body["outputs"])
    return body


def simulate_body(nodes, values, method: str, E: float | None) -> dict:
    return {
        "forces": {"nodes": _node_ids(nodes, "forces' nodes"), "values": np.asarray(values, np.float64)},
        "method": method,
        "E": E,
    }

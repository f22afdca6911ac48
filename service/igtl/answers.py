"""What the bridge sends a client besides the surface: the ``status`` STRING (JSON), and an
error in the API's words (``{code, detail}``)."""

from __future__ import annotations

import json
import math

import numpy as np

from . import protocol as p

SURFACE = "registered"
STATUS = "status"


def status_message(obj: dict, version: int) -> bytes:
    """A ``status`` STRING holding ``obj`` as JSON."""
    return p.pack(
        "STRING",
        STATUS,
        p.encode_string(json.dumps(json_safe(obj), allow_nan=False, default=float)),
        version=min(version, 2),
    )


def error_body(code: int, detail: str, retry_after: float | None = None) -> dict:
    """An error as the API words it: a 503's ``retry_after`` (seconds) passed on when it gave one."""
    body: dict = {"code": code, "detail": detail}
    if retry_after is not None:
        body["retry_after"] = retry_after
    return body


def json_safe(obj):
    """Non-finite numbers as null (a frame result may hold them: status non_finite)."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj

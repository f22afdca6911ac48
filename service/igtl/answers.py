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
    """A ``status`` STRING holding ``obj`` as JSON; an error's detail too long for a STRING (the
    API's words, a sender's names) is cut to fit, so that the answer always goes."""
    text = _json(obj)
    excess = len(text) - p.STRING_MAX  # ASCII JSON (ensure_ascii): a byte a character
    if excess > 0 and isinstance(error := obj.get("error"), dict) and isinstance(error.get("detail"), str):
        detail = _cut(error["detail"], len(json.dumps(error["detail"])) - excess)
        text = _json({**obj, "error": {**error, "detail": detail}})
    return p.pack("STRING", STATUS, p.encode_string(text), version=min(version, 2))


def _cut(text: str, size: int) -> str:
    """The longest start of ``text``, an ellipsis after it, whose JSON takes at most ``size``
    bytes (a character takes 1 to 12): cut between characters, never inside one's bytes."""
    lo, hi = 0, len(text)
    while lo < hi:  # a bisection: some 17 dumps for a STRING's worth
        mid = (lo + hi + 1) // 2
        lo, hi = (mid, hi) if len(json.dumps(text[:mid] + "…")) <= size else (lo, mid - 1)
    return text[:lo] + "…"


def _json(obj: dict) -> str:
    return json.dumps(json_safe(obj), allow_nan=False, default=float)


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

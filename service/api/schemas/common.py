"""What every body shares: strict requests, open replies, and a request's errors (a cloud over
the limit, a validation error as a 422's ``detail`` or one line)."""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, ValidationError


class TooManyPoints(ValueError):
    """A cloud over the configured limit (HTTP 413, not 422: the body is valid, just too big)."""


class _Request(BaseModel):
    model_config = ConfigDict(strict=True, extra="forbid", arbitrary_types_allowed=True)


class _Reply(BaseModel):
    model_config = ConfigDict(extra="allow")


class ErrorOut(_Reply):
    detail: str | list[dict[str, Any]]


def check_points_limit(obj: Any, max_points: int) -> None:
    """Raise TooManyPoints when a frame body's cloud is over the limit (before validating it)."""
    if not isinstance(obj, dict):
        return
    p = obj.get("points")
    n = p.shape[0] if isinstance(p, np.ndarray) and p.ndim else len(p) if isinstance(p, list) else 0
    if n > max_points:
        raise TooManyPoints(f"{n} points is over this server's limit of {max_points} per frame")


def error_list(exc: ValidationError, prefix: tuple = ("body",)) -> list[dict]:
    """A validation error as FastAPI's 422 ``detail`` list (loc, msg, type), JSON-safe."""
    out = []
    for e in exc.errors(include_url=False, include_context=False, include_input=False):
        out.append({"loc": [*prefix, *e["loc"]], "msg": e["msg"], "type": e["type"]})
    return out


def error_text(errors: list[dict]) -> str:
    """The same errors as one line (WebSocket error messages)."""
    return "; ".join(f"{'.'.join(str(p) for p in e['loc'] if p != 'body') or 'body'}: {e['msg']}" for e in errors)

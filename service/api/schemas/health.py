"""The server's health: its status and why, its limits, its sessions."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from .common import _Reply


class Limits(_Reply):
    """Every limit of service/config.py's LIMITS (all listed; these three at least)."""

    max_points: int
    max_sessions: int
    session_ttl_s: float


class SessionCount(_Reply):
    open: int
    http: int
    stream: int


class Health(_Reply):
    status: Literal["ok", "degraded"] = Field(
        description="degraded (HTTP 503): no model loaded, or the solve queue is full"
    )
    reasons: list[str] = Field([], description="why it is degraded")
    models: int
    device: str
    version: str
    limits: Limits
    instance: str = Field(description="this server process (sessions live in the process that made them)")
    sessions: SessionCount
    solver_threads: int
    skipped_models: dict[str, str] = Field(description="store entries that failed to load, and why")

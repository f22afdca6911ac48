"""The service's settings: limits, paths and pool sizes, read once from the environment.

Every field can be set as ``ELASTREG_<NAME>`` (``ELASTREG_MAX_POINTS=50000``); the validators
refuse a bad value when the server starts, not at the first request that trips over it.

>>> Settings(max_points=1000).max_points
1000
"""

from __future__ import annotations

import logging
import os
import re
import secrets
from functools import lru_cache
from pathlib import Path
from typing import Annotated

from pydantic import Field, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from .sparse_libs import missing

log = logging.getLogger(__name__)

_THREAD_ENV = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def limit_threads(n: int) -> None:
    """BLAS/OpenMP threads per solve, process-wide: the pool runs solves side by side, and
    nested BLAS threads would fight over the cores. A registration makes thousands of tiny BLAS
    calls (L-BFGS-B's own among them), which threads only slow down: measured 10x slower per
    L-BFGS-B iteration with OpenBLAS's 2 threads on a loaded 2-core machine, 1.4x unloaded.
    Libraries already loaded are limited with threadpoolctl (when installed); ones loaded later
    read the environment. The benchmark runs under the server's setting too."""
    for var in _THREAD_ENV:
        os.environ[var] = str(n)
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        log.info("threadpoolctl is not installed: BLAS threads limited through the environment only")
    else:
        threadpool_limits(limits=n)
    import torch

    torch.set_num_threads(n)


def flush_subnormals() -> None:
    """Subnormal floats flushed to zero, process-wide. Each thread keeps its own flag and a new
    thread copies its creator's, so this runs before torch makes its thread pool: set later it
    reaches the calling thread alone. A long training's gradients and Adam moments sank into
    subnormals, which the CPU handles slowly: liver epochs went from 1.8 s to 17 s by the 130th
    (docs/performance.md). Values under 1.2e-38 matter to no figure here."""
    import torch

    torch.set_flush_denormal(True)


def default_store() -> Path:
    """ELASTREG_STORE, else the project's own model_store/ beside the package."""
    env = os.environ.get("ELASTREG_STORE")
    return Path(env) if env else Path(__file__).resolve().parents[1] / "model_store"


def _instance_id() -> str:
    """A short random id per process: it names the process that holds a session."""
    return secrets.token_hex(3)


#: the longest session_ttl_s a server takes: a week
MAX_SESSION_TTL_S = 7 * 24 * 3600.0

#: the sparse factorisations ELASTREG_SOLVER may name (service/fem/linsolve.py's BACKENDS)
SOLVERS = ("pardiso", "cholmod", "superlu")

_TOKEN = r"^[A-Za-z0-9._~+/=-]{16,512}$"  # RFC 6750's token68 characters, at least 16 of them

#: the settings that bound what clients can make the server hold or do, and how long they wait:
#: /health lists them (deployment.md's limits table, every row)
LIMITS = (
    "max_points",
    "max_sessions",
    "max_sessions_per_token",
    "session_ttl_s",
    "max_body_bytes",
    "max_message_bytes",
    "max_array_elements",
    "stream_queue",
    "stream_queue_bytes",
    "max_sockets",
    "max_tokenless_sockets",
    "max_connections",
    "first_message_timeout_s",
    "body_timeout_s",
    "send_timeout_s",
    "send_min_bytes_per_s",
    "max_iter",
    "max_time_budget_ms",
    "e_range",
    "solve_queue",
    "session_queue",
    "solver_threads",
    "ws_ping_interval_s",
    "ws_ping_timeout_s",
    "drain_timeout_s",
)


def _split(value):
    """A comma-separated environment value as a tuple (a tuple or list passes through)."""
    if isinstance(value, str):
        return tuple(v.strip() for v in value.split(",") if v.strip())
    return value


def read_token_file(path: Path) -> tuple[str, ...]:
    """The tokens of a token file: one a line; blank lines and ``#`` comments ignored."""
    try:
        text = Path(path).read_text()
    except OSError as exc:
        raise ValueError(f"cannot read the token file {path}: {exc}") from None
    return tuple(t for t in (line.split("#", 1)[0].strip() for line in text.splitlines()) if t)


class Settings(BaseSettings):
    """What a server process runs with."""

    model_config = SettingsConfigDict(
        env_prefix="ELASTREG_",
        extra="ignore",
        frozen=True,
        hide_input_in_errors=True,  # no token in a log
    )

    store: Path = Field(default_factory=default_store, description="the model store folder")
    max_points: int = Field(100_000, ge=1, le=10_000_000, description="points per frame (413 over it)")
    max_sessions: int = Field(64, ge=1, le=100_000, description="open sessions and streams (503 over it)")
    # None: half of max_sessions where two tokens or more are set (one client cannot lock the
    # others out); with one token or none every client is one owner: max_sessions (_consistent)
    max_sessions_per_token: int | None = Field(
        None, ge=1, le=100_000, description="open sessions and streams of one token (503 over it; at most max_sessions)"
    )
    session_ttl_s: float = Field(600.0, gt=0, le=MAX_SESSION_TTL_S, description="idle seconds before a session expires")
    sweep_interval_s: float = Field(5.0, gt=0, le=3600, description="how often expired sessions are dropped")
    solver_threads: int = Field(2, ge=1, le=256, description="threads that run solves")
    blas_threads: int = Field(
        1, ge=0, le=256, description="BLAS/OpenMP threads per solve (0: leave the process as it is)"
    )
    max_body_bytes: int = Field(
        16 << 20, ge=1 << 10, le=1 << 31, description="bytes per HTTP request body (413 over it)"
    )
    stream_queue: int = Field(256, ge=1, le=100_000, description="frames a stream may queue before reads pause")
    # -- access (API.md, "Access") -----------------------------------------------------------------
    api_tokens: Annotated[tuple[str, ...], NoDecode] = Field(
        (), repr=False, description="bearer tokens, comma-separated (none: the server is open, loopback only)"
    )
    token_file: Path | None = Field(None, description="a file of bearer tokens, one a line (added to api_tokens)")
    allowed_origins: Annotated[tuple[str, ...], NoDecode] = Field(
        (), description="browser origins allowed to call the API cross-origin, comma-separated (scheme://host[:port])"
    )
    insecure: bool = Field(False, description="serve a non-loopback address without tokens")
    # -- limits: what one client can make the server hold or do ----------------------------------------
    max_message_bytes: int = Field(
        16 << 20, ge=1 << 10, le=1 << 31, description="bytes per WebSocket message (closed 1009 over it)"
    )
    max_array_elements: int = Field(
        1_000_000, ge=1024, le=1 << 31, description="array elements decoded per body or message (413 over it)"
    )
    stream_queue_bytes: int = Field(
        32 << 20, ge=1 << 10, le=1 << 34, description="bytes of frames a stream may queue before its reads pause"
    )
    max_sockets: int = Field(128, ge=1, le=100_000, description="open WebSockets (HTTP 503 for the next handshake)")
    max_tokenless_sockets: int = Field(
        16,
        ge=1,
        le=100_000,
        description=(
            "with tokens: WebSockets whose handshake carried no valid token, waiting for one in their first "
            "message; counted apart from max_sockets so they cannot lock out clients with a token (HTTP 503 "
            "for the next such handshake)"
        ),
    )
    max_connections: int = Field(
        512,
        ge=2,
        le=1_000_000,
        description="open TCP connections and requests in progress (uvicorn's limit_concurrency)",
    )
    first_message_timeout_s: float = Field(
        10.0, gt=0, le=3600, description="a socket without its first message is closed"
    )
    body_timeout_s: float = Field(30.0, gt=0, le=3600, description="seconds to receive a request body (408 past it)")
    send_timeout_s: float = Field(
        30.0,
        gt=0,
        le=3600,
        description=(
            "a stream, watcher or bridge client that takes no byte of a message (or acknowledges no message) "
            "for this long is closed; one that keeps taking bytes is kept, however long the message takes, "
            "down to send_min_bytes_per_s"
        ),
    )
    send_min_bytes_per_s: float = Field(
        8192.0,
        gt=0,
        le=1 << 30,
        description=(
            "a send may last send_timeout_s plus its bytes at this rate: a client that takes a message more "
            "slowly (a byte now and then to look alive) is closed"
        ),
    )
    ws_ping_interval_s: float = Field(10.0, gt=0, le=3600, description="WebSocket keepalive pings")
    ws_ping_timeout_s: float = Field(
        10.0, gt=0, le=3600, description="a socket that answers no ping for this long is dropped"
    )
    max_iter: int = Field(1000, ge=1, le=10_000, description="server-wide cap on a session's max_iter")
    max_time_budget_ms: float = Field(
        10_000.0, gt=0, le=3_600_000, description="server-wide cap on a frame's time_budget_ms (and its default)"
    )
    e_range: float = Field(1000.0, ge=1, le=1e6, description="a session's E within this factor of the model's own")
    solve_queue: int = Field(
        16, ge=0, le=100_000, description="solves waiting for a thread (503 with Retry-After over it)"
    )
    session_queue: int = Field(
        2, ge=0, le=1000, description="HTTP frames of one session waiting behind its running one"
    )
    retry_after_s: int = Field(
        1,
        ge=1,
        le=3600,
        description="Retry-After of a 503 from the solve pool (saturated, shutting down) and at the socket limit",
    )
    # a session frees up when its client closes it or the sweeper drops it idle (every
    # sweep_interval_s, 5 s by default): a retry every second would mostly meet the same full server
    session_retry_after_s: int = Field(
        5,
        ge=1,
        le=3600,
        description="Retry-After of a 503 at the session limit (sessions free up when closed or swept as idle)",
    )
    drain_timeout_s: float = Field(30.0, ge=0, le=3600, description="at shutdown: seconds to finish frames in flight")
    instance_id: str = Field(
        default_factory=_instance_id,
        pattern=r"^[A-Za-z0-9_.]{1,32}$",
        description="names this process in session ids and the X-Elastreg-Instance header",
    )
    access_log: bool = Field(False, description="uvicorn's per-request log lines")
    solver: str | None = Field(
        None, description="the sparse factorisation: pardiso, cholmod or superlu (default: the fastest installed)"
    )

    @field_validator("api_tokens", "allowed_origins", mode="before")
    @classmethod
    def _comma_separated(cls, value):
        return _split(value)

    @field_validator("api_tokens")
    @classmethod
    def _tokens(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        return _check_tokens(value, "ELASTREG_API_TOKENS")

    @field_validator("solver")
    @classmethod
    def _solver(cls, value: str | None) -> str | None:
        # here, at startup: a bad name would otherwise surface as a 422 or a 500 at the first session
        if not value:
            return None
        if value not in SOLVERS:
            raise ValueError(f"ELASTREG_SOLVER: unknown solver {value!r}; choose from {', '.join(SOLVERS)}")
        problem = missing(value)  # the probe the FEM's solvers load through
        if problem:
            usable = " or ".join(name for name in SOLVERS if missing(name) is None)
            raise ValueError(f"ELASTREG_SOLVER: {problem}; or choose {usable}")
        return value

    @field_validator("allowed_origins")
    @classmethod
    def _origins(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        out = []
        for origin in value:
            o = origin.rstrip("/").lower()
            if o == "*" or not re.fullmatch(r"(https?)://[^/\s]+", o):
                raise ValueError(f"an allowed origin is scheme://host[:port] (no path, no '*'), got {origin!r}")
            out.append(o)
        return tuple(out)

    @model_validator(mode="after")
    def _consistent(self) -> Settings:
        # a packed float64 cloud at the point limit must fit in one body and one message
        for name in ("max_body_bytes", "max_message_bytes"):
            if self.max_points * 24 > getattr(self, name):
                raise ValueError(
                    f"{name} ({getattr(self, name)}) cannot hold a packed cloud of max_points "
                    f"({self.max_points}) points: raise it to at least {self.max_points * 24 + 4096}"
                )
        if self.max_array_elements < 4 * self.max_points + 1024:  # a cloud as nested lists: m + 3m elements
            raise ValueError(
                f"max_array_elements ({self.max_array_elements}) cannot hold a cloud of max_points "
                f"({self.max_points}) points as nested lists: raise it to at least {4 * self.max_points + 1024}"
            )
        if self.stream_queue_bytes < self.max_message_bytes:
            raise ValueError(
                f"stream_queue_bytes ({self.stream_queue_bytes}) must hold one message of "
                f"max_message_bytes ({self.max_message_bytes})"
            )
        if self.token_file is not None:  # read once, here: a bad file stops the server at startup
            extra = _check_tokens(read_token_file(self.token_file), str(self.token_file))
            object.__setattr__(self, "api_tokens", tuple(dict.fromkeys(self.api_tokens + extra)))
        per_token = self.max_sessions_per_token if self.api_tokens else None
        if per_token is None and len(self.api_tokens) > 1:
            per_token = max(1, self.max_sessions // 2)
        object.__setattr__(self, "max_sessions_per_token", min(per_token or self.max_sessions, self.max_sessions))
        return self

    @property
    def limits(self) -> dict[str, float | int]:
        """The limits as /health lists them."""
        return {name: getattr(self, name) for name in LIMITS}


def _check_tokens(tokens: tuple[str, ...], where: str) -> tuple[str, ...]:
    for t in tokens:
        if not re.fullmatch(_TOKEN, t):
            raise ValueError(
                f"{where}: a token is 16 to 512 characters of A-Z a-z 0-9 . _ ~ + / = - "
                f"(got one of {len(t)} characters); make one with: "
                "python -c 'import secrets; print(secrets.token_urlsafe(32))'"
            )
    return tokens


def setting_problems(exc) -> list[str]:
    """A settings ValidationError as one line per bad setting, each naming its variable
    (``ELASTREG_*`` for a rule between settings)."""
    lines = []
    for err in exc.errors():
        msg = err["msg"].removeprefix("Value error, ")
        name = f"ELASTREG_{str(err['loc'][0]).upper()}" if err["loc"] else "ELASTREG_*"
        lines.append(msg if msg.startswith(name) else f"{name}: {msg}")
    return lines


@lru_cache
def get_settings() -> Settings:
    """The process's settings (cached: built on first use, never at import)."""
    return Settings()

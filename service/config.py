"""The service's settings: limits, paths and pool sizes, read once from the environment.

Every field can be set as ``ELASTREG_<NAME>`` (``ELASTREG_MAX_POINTS=50000``); the validators
refuse a bad value when the server starts, not at the first request that trips over it.

>>> Settings(max_points=1000).max_points
1000
"""

from __future__ import annotations

import logging
import os
import secrets
from functools import lru_cache
from pathlib import Path

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

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


def default_store() -> Path:
    """ELASTREG_STORE, else the project's own model_store/ beside the package."""
    env = os.environ.get("ELASTREG_STORE")
    return Path(env) if env else Path(__file__).resolve().parents[1] / "model_store"


def _instance_id() -> str:
    """A short random id per process: it names the process that holds a session."""
    return secrets.token_hex(3)


class Settings(BaseSettings):
    """What a server process runs with."""

    model_config = SettingsConfigDict(env_prefix="ELASTREG_", extra="ignore", frozen=True)

    store: Path = Field(default_factory=default_store, description="the model store folder")
    max_points: int = Field(100_000, ge=1, le=10_000_000, description="points per frame (413 over it)")
    max_sessions: int = Field(64, ge=1, le=100_000, description="open sessions and streams (503 over it)")
    session_ttl_s: float = Field(600.0, gt=0, le=7 * 24 * 3600, description="idle seconds before a session expires")
    sweep_interval_s: float = Field(5.0, gt=0, le=3600, description="how often expired sessions are dropped")
    solver_threads: int = Field(2, ge=1, le=256, description="threads that run solves")
    blas_threads: int = Field(
        1, ge=0, le=256, description="BLAS/OpenMP threads per solve (0: leave the process as it is)"
    )
    max_body_bytes: int = Field(64 << 20, ge=1 << 10, le=1 << 31, description="request body / WebSocket message size")
    stream_queue: int = Field(256, ge=1, le=100_000, description="frames a stream may queue before reads pause")
    instance_id: str = Field(
        default_factory=_instance_id,
        pattern=r"^[A-Za-z0-9_.]{1,32}$",
        description="names this process in session ids and the X-Elastreg-Instance header",
    )
    access_log: bool = Field(False, description="uvicorn's per-request log lines")

    @model_validator(mode="after")
    def _consistent(self) -> Settings:
        # a packed float64 cloud at the point limit must fit in one body
        if self.max_points * 24 > self.max_body_bytes:
            raise ValueError(
                f"max_body_bytes ({self.max_body_bytes}) cannot hold a packed cloud of max_points "
                f"({self.max_points}) points: raise it to at least {self.max_points * 24 + 4096}"
            )
        return self


@lru_cache
def get_settings() -> Settings:
    """The process's settings (cached: built on first use, never at import)."""
    return Settings()

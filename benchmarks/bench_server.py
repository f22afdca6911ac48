"""A server in a process of its own for the benchmarks that measure it from outside.

proc, url, log = start_server(store, {"ELASTREG_SOLVER_THREADS": "2"}, "api")
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

from service.api.server import free_port

ROOT = Path(__file__).resolve().parents[1]
HOST = "127.0.0.1"


def start_server(store: Path, env: dict[str, str], name: str) -> tuple[subprocess.Popen, str, Path]:
    """`elastreg serve` over `store` on a free loopback port with the extra `env`, its output
    in a temporary log; returns once /health answers 200 (a RuntimeError with the log's tail if
    it exits, or after 180 s)."""
    port = free_port(HOST)
    log = tempfile.NamedTemporaryFile("w+", prefix=f"elastreg-{name}-server-", suffix=".log", delete=False)
    proc = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "serve", "--store", str(store), "--host", HOST, "--port", str(port)],
        env={**os.environ, "PYTHONPATH": str(ROOT), **env},
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    url = f"http://{HOST}:{port}"
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the server exited: {Path(log.name).read_text()[-2000:]}")
        try:
            if httpx.get(url + "/health", timeout=2).status_code == 200:
                return proc, url, Path(log.name)
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    proc.kill()
    raise RuntimeError("the server did not start")

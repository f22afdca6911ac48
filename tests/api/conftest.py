"""A real server (uvicorn on a free loopback port, in a background thread) over the small
trained ``bar`` store, and frames whose answers are known."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import msgpack
import numpy as np
import pytest

from service.api.server import BackgroundServer, free_port
from service.config import Settings
from service.synthetic import sample_surface

MAX_POINTS = 3000


@dataclasses.dataclass
class Live:
    """A running server: its URL, app (for app.state) and settings."""

    server: BackgroundServer

    @property
    def url(self) -> str:
        return self.server.url

    @property
    def ws(self) -> str:
        return self.server.url.replace("http://", "ws://") + "/stream"

    @property
    def app(self):
        return self.server.app

    @property
    def settings(self) -> Settings:
        return self.server.settings


def start(store, *, wrap=None, log_level: str = "warning", **overrides) -> BackgroundServer:
    """A started server; ``wrap`` (an ASGI middleware class) wraps the whole app, outside its
    own middleware, as a deployment's or the server's may; ``log_level`` is uvicorn's."""
    # blas_threads=0: the server shares this process with the rest of the test session; leave
    # its BLAS and torch threads alone. session_queue=8: test_concurrency posts 6 frames of one
    # session at once (the default, 2, would answer some of them 503)
    defaults = {
        "max_points": MAX_POINTS,
        "max_body_bytes": 1 << 20,
        "max_message_bytes": 1 << 20,
        "blas_threads": 0,
        "session_queue": 8,
    }
    settings = Settings(store=store, **{**defaults, **overrides})
    server = BackgroundServer(settings, log_level=log_level)
    if wrap is not None:  # uvicorn loads its config's app at start-up
        server.server.config.app = wrap(server.app)
    return server.start()


@pytest.fixture(scope="session")
def live(bar_store):
    """The main test server (instance "alpha")."""
    server = start(bar_store[0], instance_id="alpha", max_sessions=24, solver_threads=2)
    yield Live(server)
    server.stop()


@pytest.fixture(scope="session")
def small(bar_store):
    """A second server process stand-in (instance "beta"): 2 sessions at most, idle ones expire
    after 2 s (swept every 0.1 s)."""
    server = start(bar_store[0], instance_id="beta", max_sessions=2, session_ttl_s=2.0, sweep_interval_s=0.1)
    yield Live(server)
    server.stop()


@pytest.fixture(scope="session")
def support(entry):
    """A patch of the bar's far half, inside the network's region."""
    mesh = entry.mesh
    region = entry.region
    return np.sort(region[mesh.nodes[region, 0] >= 2.5])


@pytest.fixture(scope="session")
def clouds(entry, support):
    """Six clouds of 200 points on the bar deformed by the network under a growing load."""
    mesh = entry.mesh
    rng = np.random.default_rng(0)
    out = []
    for t in range(6):
        g = np.tile([0.0, 0.5, 4.0 * (t + 1) / support.size], (support.size, 1))
        u = entry.network.predict(g[None], support)[0]
        pts, _, _ = sample_surface(mesh.nodes + u, mesh.surface_faces, 200, rng)
        out.append(pts)
    return out


@pytest.fixture
def http(live):
    with httpx.Client(base_url=live.url, timeout=60) as c:
        yield c


def packed(a: np.ndarray, dtype: str = "<f8") -> dict:
    a = np.ascontiguousarray(a, dtype=dtype)
    return {"dtype": dtype, "shape": list(a.shape), "data": a.tobytes()}


def mp(obj) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


MSGPACK = {"content-type": "application/msgpack", "accept": "application/msgpack"}


def unpack(data: bytes):
    """A MessagePack reply with packed arrays as arrays."""

    def walk(o):
        if isinstance(o, dict):
            if set(o) == {"dtype", "shape", "data"}:
                return np.frombuffer(o["data"], o["dtype"]).reshape(o["shape"])
            return {k: walk(v) for k, v in o.items()}
        if isinstance(o, list):
            return [walk(v) for v in o]
        return o

    return walk(msgpack.unpackb(data, raw=False))


@contextlib.contextmanager
def occupied(pool, n: int = 1, timeout: float = 60.0):
    """``n`` jobs admitted to a server's solve pool as solves are, each holding a solver thread
    (or a queue place) until the block ends: a stand-in for long FEM frames."""
    release = threading.Event()
    admitted = threading.Semaphore(0)

    async def block() -> None:
        job = asyncio.ensure_future(pool.run(release.wait, timeout))
        await asyncio.sleep(0)  # the job's first step ran: admitted, or refused (done, Overloaded)
        if not job.done():
            admitted.release()
        await job

    # each blocker reports its own admission: the pool's in_flight also moves with other jobs
    # (one left by an earlier test that ends meanwhile would hide a blocker's +1)
    threads = [threading.Thread(target=lambda: asyncio.run(block()), daemon=True) for _ in range(n)]
    for t in threads:
        t.start()
    deadline = time.monotonic() + 10
    assert all(admitted.acquire(timeout=max(0.0, deadline - time.monotonic())) for _ in threads), (
        "the blockers were not admitted"
    )
    try:
        yield release
    finally:
        release.set()
        for t in threads:
            t.join(timeout=30)


@contextlib.contextmanager
def server_process(store) -> Iterator[tuple[subprocess.Popen, str]]:
    """``elastreg serve`` in a process of its own (one a test can freeze with SIGSTOP), up, and
    its URL; killed at the block's end."""
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    argv = [sys.executable, "-m", "service.cli", "serve", "--store", str(store), "--port", str(port)]
    root = Path(__file__).resolve().parents[2]
    server = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=root)
    try:

        def up() -> bool:
            assert server.poll() is None, "the server exited"
            try:
                return httpx.get(url + "/health", timeout=2).status_code == 200
            except httpx.HTTPError:
                return False

        assert wait_for(up, 120), "the server did not start"
        yield server, url
    finally:
        server.kill()
        server.wait(30)


def wait_for(predicate, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def ws_url(live: Live) -> str:
    return live.url.replace("http://", "ws://") + "/stream"


def recv(ws, timeout=60):
    m = ws.recv(timeout=timeout)
    return unpack(m) if isinstance(m, bytes) else json.loads(m)

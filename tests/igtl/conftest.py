"""The bridge for real: an API server (uvicorn in a thread, tests/api/conftest.py's ``start``)
and a :class:`Bridge` serving OpenIGTLink on a free port in a thread of its own; clients speak
raw OpenIGTLink over TCP."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import httpx
import numpy as np
import pytest

from service.api.server import free_port
from service.igtl import protocol as p
from service.igtl.bridge import Bridge, serve
from tests.api.conftest import start


class RunningBridge:
    """``serve(bridge)`` on 127.0.0.1, a free port, in a thread with its own event loop."""

    def __init__(self, bridge: Bridge) -> None:
        self.bridge = bridge
        self.port: int | None = None
        self.error: BaseException | None = None
        self._ready = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task | None = None
        self._thread = threading.Thread(target=self._run, name="igtl-bridge", daemon=True)
        self._thread.start()
        if not self._ready.wait(60) or self.port is None:
            raise RuntimeError(f"the bridge did not start: {self.error!r}")

    def _run(self) -> None:
        async def main() -> None:
            self._loop = asyncio.get_running_loop()
            self._task = asyncio.current_task()

            def ready(port: int) -> None:
                self.port = port
                self._ready.set()

            await serve(self.bridge, "127.0.0.1", 0, ready)

        try:
            asyncio.run(main())
        except asyncio.CancelledError:
            pass
        except BaseException as exc:
            self.error = exc
        finally:
            self._ready.set()

    def stop(self) -> None:
        if self._loop is not None and self._task is not None and self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._task.cancel)
        self._thread.join(30)

    def connect(self, timeout: float = 60) -> socket.socket:
        return socket.create_connection(("127.0.0.1", self.port), timeout=timeout)

    def wait_free(self, timeout: float = 30) -> None:
        """Until no client holds the bridge's one slot (free once a client leaves, before its
        session is closed)."""
        deadline = time.monotonic() + timeout
        while self.bridge.busy and time.monotonic() < deadline:
            time.sleep(0.02)
        assert not self.bridge.busy

    def wait_sessions(self, n: int, timeout: float = 30) -> list[str]:
        """The bridge's session ids once it has opened ``n`` of them."""
        deadline = time.monotonic() + timeout
        while len(self.bridge.sessions) < n and time.monotonic() < deadline:
            time.sleep(0.02)
        assert len(self.bridge.sessions) >= n, self.bridge.sessions
        return list(self.bridge.sessions)


@pytest.fixture
def run_bridge():
    """``run_bridge(api_url, model="bar", **kw)``: a RunningBridge, stopped after the test."""
    running: list[RunningBridge] = []

    def make(api_url: str, model: str = "bar", **kw) -> RunningBridge:
        b = RunningBridge(Bridge(api_url, model, **kw))
        running.append(b)
        return b

    yield make
    for b in running:
        b.stop()


@pytest.fixture
def api_server(bar_store):
    """``api_server(**settings)``: a started API server over the bar store, stopped after the test."""
    servers = []

    def make(store=None, **overrides):
        s = start(store or bar_store[0], **overrides)
        servers.append(s)
        return s

    yield make
    for s in servers:
        s.stop()


@pytest.fixture
def api_process(bar_store, tmp_path, request):
    """An API server in its own process (`elastreg serve` over the bar store), to be stopped
    (SIGSTOP) as a hung API is: (url, process), continued and ended after the test. Parametrized
    indirectly with a dict, it serves that dict's ``store`` (default: the bar store) with its
    ``ELASTREG_*`` variables as settings."""
    env = {**os.environ, **getattr(request, "param", {})}
    port = free_port()
    store = str(env.pop("store", bar_store[0]))
    cmd = [sys.executable, "-m", "service.cli", "serve", "--store", store, "--port", str(port)]
    server = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=(tmp_path / "serve.log").open("w"), env=env)
    try:
        url = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 120
        while True:
            with contextlib.suppress(httpx.TransportError):
                if httpx.get(f"{url}/health", timeout=5).status_code == 200:
                    break
            assert server.poll() is None and time.monotonic() < deadline, (tmp_path / "serve.log").read_text()
            time.sleep(0.2)
        yield url, server
    finally:
        server.send_signal(signal.SIGCONT)
        server.terminate()
        server.wait(30)


def exactly(sock: socket.socket, n: int) -> bytes:
    buf = b""
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ConnectionError(f"the bridge closed the connection after {len(buf)} of {n} bytes")
        buf += chunk
    return buf


def read_message(sock: socket.socket) -> p.Message:
    version, mtype, device, ts, size, crc = p.parse_header(exactly(sock, p.HEADER_SIZE))
    return p.parse_body(version, mtype, device, ts, exactly(sock, size), crc)


def read_answer(sock: socket.socket) -> tuple[p.PolyData | None, dict]:
    """A frame's answer: the registered surface (None when it failed) and the status's JSON."""
    surface = None
    while True:
        msg = read_message(sock)
        if msg.type == "POLYDATA" and msg.device == "registered":
            surface = p.decode_polydata(msg.content)
        elif msg.type == "STRING" and msg.device == "status":
            return surface, json.loads(p.decode_string(msg.content))


def point_frame(points: np.ndarray, version: int = 1) -> bytes:
    """A POINT message named ``cloud`` (one 136-byte item a point), packed here from the spec."""
    pts = np.asarray(points, ">f4").reshape(-1, 3)
    items = np.zeros((len(pts), p.POINT_ITEM), np.uint8)
    items[:, 100:112] = pts.view(np.uint8).reshape(-1, 12)
    return p.pack("POINT", "cloud", items.tobytes(), version=version)


def polydata_frame(points: np.ndarray) -> bytes:
    """A POLYDATA message named ``cloud``: points only."""
    return p.pack("POLYDATA", "cloud", p.encode_polydata(points, np.zeros((0, 3), int)))


def surface_cloud(mesh, n: int = 120, seed: int = 0) -> np.ndarray:
    """Points on a model's boundary (its surface nodes), float32 as OpenIGTLink carries them."""
    nodes = np.asarray(mesh["nodes"])[np.asarray(mesh["surface_nodes"])]
    rng = np.random.default_rng(seed)
    return nodes[rng.choice(len(nodes), n, replace=len(nodes) < n)].astype(np.float32)


def get_mesh(url: str, model: str) -> dict:
    return httpx.get(f"{url}/models/{model}/mesh", timeout=30).json()


def registered(answer, n_surface: int) -> dict:
    """The status of a frame that was registered (no error, the whole surface back)."""
    surface, status = answer
    assert "error" not in status, status
    assert surface is not None and len(surface.points) == n_surface
    return status


def is_open(url: str, sid: str) -> bool:
    """Whether the API holds session ``sid`` (200), or has closed it (404)."""
    code = httpx.get(f"{url}/sessions/{sid}", timeout=10).status_code
    assert code in (200, 404), code
    return code == 200


def wait_closed(url: str, sid: str, timeout: float = 20) -> None:
    deadline = time.monotonic() + timeout
    while is_open(url, sid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not is_open(url, sid)

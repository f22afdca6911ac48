"""Scale-out: `elastreg serve --workers 2` (two processes on one port). WebSocket streams work
whichever process accepts them; an HTTP session's frames on a connection that reaches the other
process get the affinity 404, never another session's answer. Part of the default suite: this is
what docs/deployment.md says of --workers, checked (about 20 s: two processes load torch)."""

from __future__ import annotations

import collections
import subprocess
import sys
import time

import httpx

from clients import Client
from clients.client import encode
from service.api.server import free_port


def test_two_worker_processes(bar_store, clouds, support):
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "service.cli",
            "serve",
            "--store",
            str(bar_store[0]),
            "--port",
            str(port),
            "--workers",
            "2",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 120
        seen = collections.Counter()
        while len(seen) < 2 and time.monotonic() < deadline:
            try:
                with httpx.Client() as c:  # a fresh connection each time
                    seen[c.get(url + "/health", timeout=2).json()["instance"]] += 1
            except httpx.HTTPError:
                time.sleep(0.2)
        assert len(seen) == 2, seen
        with Client(url) as api:
            streams = [api.stream("bar", support=support) for _ in range(6)]
            assert {s.session.split("-")[0] for s in streams} <= set(seen)
            assert all(s.frame(clouds[0])["displacement"].shape == (81, 3) for s in streams)
            for s in streams:
                s.close()
            session = api.open_session("bar", support=support)
            owner = session.id.split("-")[0]
            replies = collections.Counter()
            for _ in range(20):
                with httpx.Client(
                    base_url=url, headers={"content-type": "application/msgpack", "accept": "application/json"}
                ) as c:
                    r = c.post(f"/sessions/{session.id}/frames", content=encode({"points": clouds[1]}, "msgpack"))
                    replies[r.status_code] += 1
                    assert (r.status_code == 200) == (r.headers["x-elastreg-instance"] == owner)
                    if r.status_code == 404:
                        assert owner in r.json()["detail"] and "affinity" in r.json()["detail"]
            assert set(replies) <= {200, 404}
            assert session.frame(clouds[2])["status"]  # the client's own keep-alive connection
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def test_ctrl_c_stops_one_process_cleanly(bar_store):
    """Ctrl-C (SIGINT) on `elastreg serve`: drained and stopped with status 0, no traceback
    (the one-process server ran uvicorn's loop itself, and a KeyboardInterrupt escaped it)."""
    import signal

    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "serve", "--store", str(bar_store[0]), "--port", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            try:
                if httpx.get(f"http://127.0.0.1:{port}/health", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 0 and "Traceback" not in err, err[-2000:]

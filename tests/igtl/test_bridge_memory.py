"""A large cloud costs the bridge about its body once: the body is read into one buffer (not a
reader's buffer and a copy of it), a version-2 body's content is that buffer trimmed in place,
and a POLYDATA's points are decoded where they lie."""

from __future__ import annotations

import gc
import select
import socket
import subprocess
import sys
import threading
import time
import tracemalloc
import weakref
from pathlib import Path

import numpy as np
import pytest

from service.api.server import free_port
from service.igtl import protocol as p

from .conftest import get_mesh, point_frame, polydata_frame, read_answer, registered, surface_cloud, wait_closed

#: the peak of the bridge's traced allocations for one message, over its body (2.0-2.2 before)
BOUND = 1.6


def traced_answer(bridge, message: bytes) -> tuple:
    """Send `message` on a new connection once its session is open: the answer (surface, status)
    and the bridge's traced peak over what it held before the message."""
    tracemalloc.start()
    try:
        with bridge.connect() as sock:
            bridge.wait_sessions(1)
            time.sleep(0.2)  # the session's own allocations settle before the message's are counted
            base = tracemalloc.get_traced_memory()[0]
            tracemalloc.reset_peak()
            sock.sendall(message)
            surface, status = read_answer(sock)
            return surface, status, tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("kind, n", [("POLYDATA", 1_000_000), ("POINT", 100_000)])
@pytest.mark.parametrize("version", [1, 2])
def test_a_large_cloud_costs_about_its_body_once(kind, n, version, api_server, run_bridge):
    """Over the API's max_points, so the bridge answers 413 itself: the figure is the bridge's
    reading and decoding alone (12 MB and 13.6 MB bodies)."""
    api = api_server()
    cloud = np.random.default_rng(0).random((n, 3), np.float32)
    message = polydata_frame(cloud) if kind == "POLYDATA" else point_frame(cloud)
    if version == 2:  # the same content behind an extended header and metadata
        message = p.pack(kind, "cloud", message[p.HEADER_SIZE :], version=2, metadata={"unit": "m"})
    body = len(message) - p.HEADER_SIZE
    bridge = run_bridge(api.url)
    surface, status, peak = traced_answer(bridge, message)
    assert surface is None and status["error"]["code"] == 413, status
    assert peak < BOUND * body, f"peak {peak / 1e6:.1f} MB for a body of {body / 1e6:.1f} MB ({peak / body:.2f}x)"


def test_many_tiny_attributes_cost_about_their_body_once(api_server, run_bridge):
    """A POLYDATA cloud with 400,000 distinctly named empty attributes (5.5 MB): the bridge built
    an array, a name and a head for each (about 20 times the body), though it uses none. Over the
    API's max_points, so the bridge answers 413 itself: the figure is its decoding alone."""
    api = api_server()
    cloud = np.random.default_rng(0).random((4000, 3), np.float32)
    count = 400_000
    heads = np.zeros(count, [("kind", "u1"), ("ncomp", "u1"), ("items", ">u4")])
    heads["ncomp"] = 1  # scalars of no items: a name is all each one holds
    names = b"".join(b"a%d\0" % i for i in range(count))
    names += b"\0" * (len(names) % 2)
    body = bytearray(polydata_frame(cloud)[p.HEADER_SIZE :])
    body[36:40] = count.to_bytes(4, "big")  # the POLYDATA header's attribute count
    message = p.pack("POLYDATA", "cloud", bytes(body) + heads.tobytes() + names)
    size = len(message) - p.HEADER_SIZE
    bridge = run_bridge(api.url)
    surface, status, peak = traced_answer(bridge, message)
    assert surface is None and status["error"]["code"] == 413, status
    assert peak < BOUND * size, f"peak {peak / 1e6:.1f} MB for a body of {size / 1e6:.1f} MB ({peak / size:.2f}x)"


def rss_mib(pid: int) -> float:
    """A process's resident memory now (VmRSS of /proc/PID/status), in MiB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError(f"no VmRSS for process {pid}")


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads /proc")
def test_a_header_alone_costs_nothing_and_a_refused_body_is_not_held(api_server):
    """The bridge in its own process (`elastreg igtl`), its RSS from /proc: a 58-byte header
    announcing 256 MiB with nothing after made it allocate 256 MiB at once, held for up to
    body_timeout_s; a version-3 header (refused) with a 64 MiB body behind it peaked at about
    twice the body (read whole, then copied). Now the buffer grows with what comes, and a
    refused body is skipped as it comes."""
    api = api_server()
    port = free_port()
    cmd = [sys.executable, "-m", "service.cli", "igtl", "--model", "bar", "--server", api.url, "--port", str(port)]
    bridge = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        assert "OpenIGTLink on" in bridge.stdout.readline()
        with socket.create_connection(("127.0.0.1", port), timeout=60) as sock:
            time.sleep(0.5)  # its session opened
            base = rss_mib(bridge.pid)
            sock.sendall(p.HEADER.pack(1, b"POINT", b"cloud", 0, 0, p.MAX_BODY, 0))
            time.sleep(1.0)
            grown = rss_mib(bridge.pid) - base
        assert grown < 32, f"+{grown:.0f} MiB for a header announcing {p.MAX_BODY >> 20} MiB"
        body = bytes(64 << 20)
        refused = p.HEADER.pack(3, b"POINT", b"cloud", 0, 0, len(body), 0) + body
        with socket.create_connection(("127.0.0.1", port), timeout=60) as sock:
            time.sleep(0.5)
            base = peak = rss_mib(bridge.pid)
            sender = threading.Thread(target=sock.sendall, args=(refused,))
            sender.start()
            while sender.is_alive() or not select.select([sock], [], [], 0)[0]:
                peak = max(peak, rss_mib(bridge.pid))
                time.sleep(0.005)
            sender.join()
            assert read_answer(sock)[1]["error"]["code"] == 400
        assert peak - base < 32, f"+{peak - base:.0f} MiB for a refused body of {len(body) >> 20} MiB"
    finally:
        bridge.kill()
        bridge.wait(30)


def test_a_client_that_left_is_not_held_by_the_bridge(api_server, run_bridge):
    """The bridge kept the last client's connection (its reader's buffer, its API stream) until
    the next client came, for the reconnect's wait: once its teardown is over it is freed."""
    api = api_server()
    mesh = get_mesh(api.url, "bar")
    bridge = run_bridge(api.url)
    with bridge.connect() as sock:
        sock.sendall(point_frame(surface_cloud(mesh)))
        sid = registered(read_answer(sock), len(mesh["surface_nodes"]))["session"]
        held = bridge.bridge._client
        assert held is not None
        gone = weakref.ref(held)
        del held
    wait_closed(api.url, sid)
    deadline = time.monotonic() + 10
    while gone() is not None and time.monotonic() < deadline:  # its teardown ends just after the session's close
        gc.collect()
        time.sleep(0.05)
    assert gone() is None, "the bridge still holds the connection of a client that left"

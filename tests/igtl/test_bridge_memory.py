"""A large cloud costs the bridge about its body once: the body is read into one buffer (not a
reader's buffer and a copy of it), a version-2 body's content is that buffer trimmed in place,
and a POLYDATA's points are decoded where they lie."""

from __future__ import annotations

import time
import tracemalloc

import numpy as np
import pytest

from service.igtl import protocol as p

from .conftest import point_frame, polydata_frame, read_answer

#: the peak of the bridge's traced allocations for one message, over its body (2.0-2.2 before)
BOUND = 1.6


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
    tracemalloc.start()
    try:
        with bridge.connect() as sock:
            bridge.wait_sessions(1)
            time.sleep(0.2)  # the session's own allocations settle before the message's are counted
            base = tracemalloc.get_traced_memory()[0]
            tracemalloc.reset_peak()
            sock.sendall(message)
            surface, status = read_answer(sock)
            peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert surface is None and status["error"]["code"] == 413, status
    assert peak < BOUND * body, f"peak {peak / 1e6:.1f} MB for a body of {body / 1e6:.1f} MB ({peak / body:.2f}x)"

"""``elastreg igtl`` as a real subprocess on a free port, in front of the test server: clouds sent
with pyigtl (POLYDATA and POINT, header versions 1 and 2) come back as the registered surface,
equal to what the HTTP API returns for the same frames; malformed and foreign messages do not
break the connection."""

from __future__ import annotations

import json
import socket
import subprocess
import sys

import numpy as np
import pytest

pyigtl = pytest.importorskip("pyigtl")

from service.api.server import free_port  # noqa: E402
from service.igtl import protocol as p  # noqa: E402


def read_message(sock: socket.socket) -> p.Message:
    def exactly(n: int) -> bytes:
        buf = b""
        while len(buf) < n:
            chunk = sock.recv(n - len(buf))
            if not chunk:
                raise ConnectionError("the bridge closed the connection")
            buf += chunk
        return buf

    version, mtype, device, ts, size, crc = p.parse_header(exactly(p.HEADER_SIZE))
    return p.parse_body(version, mtype, device, ts, exactly(size), crc)


@pytest.fixture
def bridge(live, support, tmp_path):
    port = free_port()
    ids = tmp_path / "support.txt"
    ids.write_text(" ".join(map(str, support.tolist())))
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "service.cli",
            "igtl",
            "--model",
            "bar",
            "--server",
            live.url,
            "--port",
            str(port),
            "--support",
            str(ids),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    line = proc.stdout.readline()
    assert "OpenIGTLink on" in line, line + proc.stdout.read() if proc.poll() is not None else line
    yield port
    proc.terminate()
    proc.wait(10)


def test_bridge_surface_equals_the_http_api(live, http, bridge, entry, support, clouds):
    mesh = entry.mesh
    sent = [c.astype(np.float32) for c in clouds[:4]]  # OpenIGTLink carries float32
    r = http.post("/sessions", json={"model": "bar", "support": support.tolist()})
    sid = r.json()["session"]
    with socket.create_connection(("127.0.0.1", bridge), timeout=60) as sock:
        # noise first: a foreign message (ignored), then a corrupt one (answered, survived)
        sock.sendall(pyigtl.TransformMessage(np.eye(4), device_name="probe").pack())
        bad = bytearray(pyigtl.PolyDataMessage(points=sent[0], device_name="cloud").pack())
        bad[-1] ^= 0xFF
        sock.sendall(bytes(bad))
        err = read_message(sock)
        assert (err.type, err.device) == ("STRING", "status")
        error = json.loads(p.decode_string(err.content))["error"]
        assert error["code"] == 400 and "CRC" in error["detail"], error
        for t, pts in enumerate(sent):
            if t % 2:
                msg = pyigtl.PointMessage(positions=pts, device_name="cloud")
            else:
                tris = mesh.surface_faces[:10]
                msg = pyigtl.PolyDataMessage(
                    points=pts, polygons=np.c_[np.full(10, 3), tris].ravel(), device_name="cloud"
                )
            msg.header_version = 2 if t == 2 else 1
            sock.sendall(msg.pack())
            surf, status = read_message(sock), read_message(sock)
            assert (surf.type, surf.device, surf.version) == (
                "POLYDATA",
                "registered",
                msg.header_version,
            )
            assert (status.type, status.device) == ("STRING", "status")
            got = p.decode_polydata(surf.content)
            st = json.loads(p.decode_string(status.content))
            assert st["frame_id"] == t and isinstance(st["converged"], bool) and len(st["net_force"]) == 3
            assert {"status", "error_estimate", "timing_ms"} <= set(st)

            want = http.post(f"/sessions/{sid}/frames", json={"points": pts.astype(float).tolist()}).json()
            x = mesh.nodes[mesh.surface_nodes] + np.asarray(want["displacement"])[mesh.surface_nodes]
            np.testing.assert_allclose(got.points, x.astype(np.float32), rtol=0, atol=1e-6)
            np.testing.assert_allclose(st["net_force"], want["net_force"], rtol=1e-6, atol=1e-9)
            # outward triangles: the model's surface faces, renumbered onto the surface nodes
            np.testing.assert_array_equal(mesh.surface_nodes[got.triangles], mesh.surface_faces)
    http.delete(f"/sessions/{sid}")


def test_a_session_the_api_refuses_is_reported_to_the_client(bar_store, tmp_path):
    """The API refuses the bridge's session when a client connects (at its session limit: a
    refusal the bridge's start-up check cannot foresee, since settings it refuses stop the
    bridge before it listens): the OpenIGTLink client gets a status saying so, not a connection
    closed without a word."""
    from clients import Client

    from .conftest import start

    server = start(bar_store[0], max_sessions=1)
    port = free_port()
    proc = None
    try:
        with Client(server.url) as api:
            held = api.open_session("bar")  # the API's one session, held while the bridge starts
            proc = subprocess.Popen(
                [sys.executable, "-m", "service.cli", "igtl", "--model", "bar", "--server", server.url,
                 "--port", str(port)],
                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            )  # fmt: skip
            lines = [proc.stdout.readline() for _ in range(2)]
            assert "could not be checked at start" in lines[0] and "OpenIGTLink on" in lines[1], lines
            with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
                msg = read_message(sock)
                assert msg.type == "STRING" and msg.device == "status"
                status = json.loads(p.decode_string(msg.content))
                assert status["error"]["code"] == 503 and "refused the session" in status["error"]["detail"], status
            held.close()
    finally:
        if proc is not None:
            proc.terminate()
            proc.wait(10)
        server.stop()

"""Ctrl-C on ``elastreg igtl`` with a client connected: the client is told and closed, its
session closed, and the command says ``interrupted`` in one line and exits 130, as
``elastreg demo`` and ``train`` do."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys

from service.api.server import free_port
from service.igtl import protocol as p

from .conftest import get_mesh, point_frame, read_answer, read_message, registered, surface_cloud, wait_closed


def test_ctrl_c_with_a_client_connected_is_one_line_and_exit_130(api_server):
    api = api_server()
    mesh = get_mesh(api.url, "bar")
    port = free_port()
    cmd = [sys.executable, "-m", "service.cli", "igtl", "--model", "bar", "--server", api.url, "--port", str(port)]
    bridge = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = bridge.stdout.readline()
        assert "OpenIGTLink on" in line, line
        with socket.create_connection(("127.0.0.1", port), timeout=60) as sock:
            sock.sendall(point_frame(surface_cloud(mesh)))
            sid = registered(read_answer(sock), len(mesh["surface_nodes"]))["session"]
            bridge.send_signal(signal.SIGINT)
            last = read_message(sock)  # told why, then closed
            assert json.loads(p.decode_string(last.content))["error"] == {
                "code": 503,
                "detail": "the bridge is stopping",
            }
            assert sock.recv(1) == b""
        _, err = bridge.communicate(timeout=60)
    finally:
        bridge.kill()
    assert bridge.returncode == 130 and err.strip().splitlines() == ["interrupted"], err
    wait_closed(api.url, sid)

"""``elastreg igtl`` that cannot start says why in one line on stderr and exits 1: a model the
API does not have, an API that is not there, a port already in use, a token the API refuses."""

from __future__ import annotations

import socket
import subprocess
import sys

import pytest

from service.api.server import free_port

TOKEN = "igtl-test-token-0123456789"


def igtl(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "service.cli", "igtl", *args], capture_output=True, text=True, timeout=120
    )


@pytest.mark.parametrize("case", ["unknown model", "API not up", "port in use", "bad token"])
def test_a_bridge_that_cannot_start_says_why_in_one_line(case, api_server):
    api = api_server(api_tokens=TOKEN) if case == "bad token" else api_server()
    args = ["--model", "bar", "--server", api.url, "--port", str(free_port())]
    words = "refused model 'bar'"
    with socket.socket() as busy:
        if case == "unknown model":
            args[1], words = "bra", "refused model 'bra': 404"
        elif case == "API not up":
            args[3], words = f"http://127.0.0.1:{free_port()}", "cannot be reached"
        elif case == "port in use":
            busy.bind(("127.0.0.1", 0))
            busy.listen()
            args[5], words = str(busy.getsockname()[1]), "cannot listen on 127.0.0.1"
        else:
            args += ["--token", "not-the-token-0123456789"]
            words = "refused model 'bar': 401"
        r = igtl(*args)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 1 and len(lines) == 1, r.stderr
    assert lines[0].startswith("error: ") and words in lines[0], lines

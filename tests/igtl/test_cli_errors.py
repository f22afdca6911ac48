"""``elastreg igtl`` that cannot start says why in one line on stderr and exits 1: a model the
API does not have, an API that is not there, a port already in use, a token the API refuses. A
wrong command line (a --support file it cannot read, settings the API refuses) is one line and
exit 2."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys

import pytest

from service.api.server import free_port

from .conftest import get_mesh

TOKEN = "igtl-test-token-0123456789"


def igtl(*args: str, prefix: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
    return subprocess.run(
        [*prefix, sys.executable, "-m", "service.cli", "igtl", *args], capture_output=True, text=True, timeout=120
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


@pytest.mark.parametrize("host", ["nosuch.invalid", "256.1.1.1"])
def test_a_host_that_does_not_resolve_is_named_so_in_one_line(host, api_server):
    """getaddrinfo's failure was told through os.strerror: "Unknown error -2"."""
    port = free_port()
    r = igtl("--model", "bar", "--server", api_server().url, "--port", str(port), "--host", host)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 1 and len(lines) == 1, r.stderr
    assert lines[0].startswith(f"error: cannot listen on {host}:{port}: the host does not resolve ("), lines
    assert "Unknown error" not in lines[0], lines


# (case, the file's content, words of the one line): each a --support the bridge cannot read
UNREADABLE_SUPPORT = [
    ("not ids", "1 2 3.5\n", "cannot read node ids from {f}: invalid literal for int() with base 10: '3.5'"),
    ("not UTF-8", b"\xff\xfe1\n", "cannot read node ids from {f}: 'utf-8' codec can't decode byte 0xff"),
    ("no file", None, "cannot read node ids from {f}: [Errno 2] No such file or directory"),
    ("no id", "# none yet\n", "{f} holds no node id"),
    ("a folder", "", "cannot read node ids from {f}: [Errno 21] Is a directory"),
    ("no read permission", "1 2\n", "cannot read node ids from {f}: [Errno 13] Permission denied"),
    ("an empty name", None, "cannot read node ids from .: [Errno 21] Is a directory"),
]


@pytest.mark.parametrize("case, content, words", UNREADABLE_SUPPORT, ids=[c[0] for c in UNREADABLE_SUPPORT])
def test_a_support_file_it_cannot_read_is_one_line_and_exit_2(case, content, words, tmp_path):
    """--support is read before the bridge starts, with a scene's support_file's rules (several
    ids a line allowed): a file it cannot read is a wrong command line, as ids the API refuses
    are: one line naming the flag, exit 2 (it was exit 1, as an API that is not up; an empty
    name was taken as no --support at all)."""
    ids = tmp_path / "support.txt"
    prefix: tuple[str, ...] = ()
    if case == "a folder":
        ids.mkdir()
    elif isinstance(content, bytes):
        ids.write_bytes(content)
    elif content is not None:
        ids.write_text(content)
    if case == "no read permission":
        ids.chmod(0)
        if os.geteuid() == 0:  # root reads any file: drop the capabilities that let it
            if shutil.which("setpriv") is None:
                pytest.skip("root reads any file, and setpriv (util-linux) is not here to drop that")
            prefix = ("setpriv", "--bounding-set", "-dac_override,-dac_read_search")
    name = "" if case == "an empty name" else str(ids)
    r = igtl("--model", "bar", "--server", f"http://127.0.0.1:{free_port()}", "--support", name, prefix=prefix)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert lines[0].startswith("error: --support: ") and words.format(f=ids) in lines[0], lines


def test_a_support_file_it_reads_goes_on_to_the_api(tmp_path):
    """Read as a scene's support_file (ids on one line, a comment): the API is next, and an API
    that is not up is a bridge that cannot start, exit 1."""
    ids = tmp_path / "support.txt"
    ids.write_text("1 2 # the patch\n3\n")
    r = igtl("--model", "bar", "--server", f"http://127.0.0.1:{free_port()}", "--support", str(ids))
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 1 and len(lines) == 1, r.stderr
    assert lines[0].startswith("error: ") and "cannot be reached" in lines[0], lines


@pytest.mark.parametrize("name", ["abcdefghijklmnopqrstuvwxyz", "wolkè", " cloud", ""])
def test_a_device_name_no_header_can_carry_is_refused_at_parse_time(name):
    """Over 20 bytes (or not ASCII, or padded) no message names it: nothing would be answered."""
    r = igtl("--model", "bar", "--server", f"http://127.0.0.1:{free_port()}", "--device", name)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("elastreg igtl: error: argument --device: a device name is")


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", "soon"])
def test_an_idle_timeout_that_is_no_positive_time_is_refused_at_parse_time(value):
    r = igtl("--model", "bar", "--server", f"http://127.0.0.1:{free_port()}", "--idle-timeout", value)
    assert r.returncode == 2, r.stderr
    assert "argument --idle-timeout: must be a positive finite number" in r.stderr.strip().splitlines()[-1]


@pytest.mark.parametrize("case", ["past the nodes", "a fixed node", "iterations past the server's cap"])
def test_settings_the_model_refuses_are_one_line_and_exit_2_before_listening(case, api_server, tmp_path):
    """--support ids the model cannot take (past its node count, on a fixed node) were sent only
    when a client connected, and each client was refused in turn; the API's own check, made at
    start, refuses them in one line naming the flag, exit 2, before the bridge listens (a
    --max-iter past the server's cap, which only the server knows, too)."""
    api = api_server()
    mesh = get_mesh(api.url, "bar")
    n = len(mesh["nodes"])
    free = sorted(set(mesh["surface_nodes"]) - set(mesh["fixed_nodes"]))
    ids = tmp_path / "support.txt"
    args = ["--model", "bar", "--server", api.url, "--port", str(free_port())]
    if case == "past the nodes":
        ids.write_text(f"{free[0]} {n}\n")
        args += ["--support", str(ids)]
        words = f"--support: support node ids must lie in 0..{n - 1}"
    elif case == "a fixed node":
        ids.write_text(f"{free[0]} {mesh['fixed_nodes'][0]}\n")
        args += ["--support", str(ids)]
        words = "--support: support contains fixed nodes"
    else:  # a whole number >= 1 passes the command line (an --alpha below zero no longer does)
        args += ["--max-iter", "1000000"]
        words = "--max-iter: "
    r = igtl(*args)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert lines[0].startswith("error: ") and words in lines[0], lines
    assert "OpenIGTLink on" not in r.stdout, r.stdout  # it never listened

"""What a client's messages make the bridge log and remember is bounded: a flood of messages
named anything and of malformed ones costs a few lines and a fixed number of remembered names,
the lines left out are counted in one, and a name is still warned of the first time it comes."""

from __future__ import annotations

import logging
import time

from service.igtl import lograte
from service.igtl import protocol as p

from .conftest import get_mesh, point_frame, read_answer, registered, surface_cloud

N = 1000  # messages of each kind: four times the names kept


def igtl_lines(caplog, level: int) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name.startswith("service.igtl") and r.levelno == level]


def test_a_flood_of_ignored_and_malformed_messages_is_bounded(api_server, run_bridge, caplog, monkeypatch):
    monkeypatch.setattr(lograte, "PERIOD", 2.0)  # the count of lines left out comes within the test
    caplog.set_level(logging.WARNING, logger="service.igtl")
    api = api_server()
    mesh = get_mesh(api.url, "bar")
    frame = point_frame(surface_cloud(mesh))
    bridge = run_bridge(api.url)
    with bridge.connect() as sock:
        sock.sendall(b"".join(p.pack("TRANSFORM", f"d{i}", b"") for i in range(N)))
        sock.sendall(p.pack("POINT", "cloud", b"", version=3) * 50)  # malformed: each answered 400
        sock.sendall(frame)
        for _ in range(50):
            assert read_answer(sock)[1]["error"]["code"] == 400
        registered(read_answer(sock), len(mesh["surface_nodes"]))
        assert len(bridge.bridge._ignored) <= lograte.SEEN_KEPT
        warned = igtl_lines(caplog, logging.WARNING)
        assert len(warned) <= lograte.BURST, warned[-3:]
        time.sleep(lograte.PERIOD + 0.5)  # the period ends: the lines left out are counted
        lines = igtl_lines(caplog, logging.WARNING)
        counted = [int(w.split()[0]) for w in lines if "were not logged" in w]
        assert counted and sum(counted) + len(lines) - len(counted) == N + 50, lines[-3:]
        # a name kept is not warned of again; a new name is, the first time
        caplog.clear()
        sock.sendall(p.pack("TRANSFORM", f"d{N - 1}", b"") + p.pack("TRANSFORM", "new", b"") + frame)
        registered(read_answer(sock), len(mesh["surface_nodes"]))
        assert [w for w in igtl_lines(caplog, logging.WARNING) if "ignored" in w] == [
            "ignored a TRANSFORM message named 'new' (frames are POLYDATA or POINT named 'cloud')"
        ]


def test_seen_keeps_the_most_recent_names():
    seen = lograte.Seen(kept=3)
    assert [seen.first(k) for k in "abcab"] == [True, True, True, False, False]
    assert seen.first("d") and len(seen) == 3  # "c", the least recently seen, is forgotten
    assert seen.first("c") and not seen.first("d")  # "c" again, "a" forgotten for it

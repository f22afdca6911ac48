"""Figures for the frontends (about a minute): the viewer watching a 10 Hz stream (frames drawn
per second, end-to-end latency from a frame's send to its picture on screen), the OpenIGTLink
bridge's round trip per frame against the WebSocket's for the same frames, and a session's
frame time with three watchers against none (the server in its own process).

    python benchmarks/frontends_bench.py [--model beam] [--store model_store] [--seconds 15]

Writes reports/frontends/frontends.json (machine, commit, figures) and prints the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _watch_10hz(url: str, model: str, clouds, support, seconds: float) -> dict:
    """A Python client streams at 10 Hz; the viewer (headless chromium) watches its session."""
    from playwright.sync_api import sync_playwright

    from clients import Client

    sent: dict[int, float] = {}
    with Client(url) as api, api.stream(model, support=support) as stream, sync_playwright() as pw:
        browser = pw.chromium.launch(
            executable_path=shutil.which("chromium"),
            args=["--no-sandbox", "--disable-gpu", "--disable-background-networking"],
        )
        page = browser.new_page(viewport={"width": 1000, "height": 700})
        page.goto(f"{url}/viewer?session={stream.session}")
        page.wait_for_function("() => window.elastregViewer.model !== null", timeout=60_000)
        stream.frame(clouds[0], frame_id=-1)  # warm up
        k, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            due = t0 + k * 0.1
            time.sleep(max(0.0, due - time.perf_counter()))
            sent[k] = 1e3 * time.time()
            stream.send(clouds[k % len(clouds)], frame_id=k)
            stream.recv()
            k += 1
        time.sleep(1.0)
        log = page.evaluate("() => window.elastregViewer.renderLog")
        err = page.evaluate("() => window.elastregViewer.lastError")
        page.screenshot(path=str(ROOT / "reports/frontends/viewer-watch.png"))
        browser.close()
    shown = [r for r in log if isinstance(r["frame_id"], int) and r["frame_id"] in sent]
    latency = [r["t"] - sent[r["frame_id"]] for r in shown]
    span = (shown[-1]["t"] - shown[0]["t"]) / 1e3 if len(shown) > 1 else float("nan")
    return {
        "frames_sent": k,
        "frames_drawn": len(shown),
        "stream_hz": k / seconds,
        "drawn_per_s": (len(shown) - 1) / span,
        "last_error": err,
        "latency_ms": {
            "median": float(np.median(latency)),
            "p95": float(np.percentile(latency, 95)),
            "max": float(np.max(latency)),
        },
    }


def _bridge_vs_ws(url: str, model: str, clouds, support, frames: int) -> dict:
    """The same frames through `elastreg igtl` (POLYDATA in; surface and status out) and over
    the WebSocket (MessagePack), alternating frame by frame."""
    import pyigtl

    from clients import Client
    from service.api.server import free_port
    from service.igtl import protocol as p

    port = free_port()
    ids = ROOT / "reports/frontends/.support.txt"
    ids.write_text(" ".join(map(str, np.asarray(support).tolist())))
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "service.cli",
            "igtl",
            "--model",
            model,
            "--server",
            url,
            "--port",
            str(port),
            "--support",
            str(ids),
        ],
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        assert "OpenIGTLink on" in proc.stdout.readline()
        sock = socket.create_connection(("127.0.0.1", port))
        buf = sock.makefile("rb")

        def message():
            v, t, d, ts, size, crc = p.parse_header(buf.read(p.HEADER_SIZE))
            return p.parse_body(v, t, d, ts, buf.read(size), crc)

        ws_ms, igtl_ms = [], []
        with Client(url) as api, api.stream(model, support=support) as stream:
            for i in range(frames + 3):
                pts = clouds[i % len(clouds)].astype(np.float32)
                t0 = time.perf_counter()
                stream.frame(pts.astype(np.float64), frame_id=i)
                t1 = time.perf_counter()
                sock.sendall(pyigtl.PolyDataMessage(points=pts, device_name="cloud").pack())
                message(), message()
                t2 = time.perf_counter()
                if i >= 3:  # the first frames warm both paths
                    ws_ms.append(1e3 * (t1 - t0))
                    igtl_ms.append(1e3 * (t2 - t1))
        sock.close()
    finally:
        proc.terminate()
        proc.wait(10)
        ids.unlink(missing_ok=True)
    ws, ig = float(np.median(ws_ms)), float(np.median(igtl_ms))
    return {
        "frames": frames,
        "points": int(len(clouds[0])),
        "websocket_ms_median": ws,
        "bridge_ms_median": ig,
        "ratio_bridge_to_websocket": ig / ws,
        "websocket_ms_p95": float(np.percentile(ws_ms, 95)),
        "bridge_ms_p95": float(np.percentile(igtl_ms, 95)),
    }


def _watchers_cost(store: str, model: str, clouds, support, blocks: int = 5) -> dict:
    """A session's HTTP frames with three watchers (another process) against none, in blocks of
    10 frames interleaved, the server in its own process (`elastreg serve`) as in production."""
    import httpx

    from service.api.server import free_port

    watchers = (ROOT / "tests/api/test_watch.py").read_text().split('WATCHERS = """')[1].split('"""')[0]
    port = free_port()
    cmd = [sys.executable, "-m", "service.cli", "serve", "--store", store, "--port", str(port)]
    server = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=ROOT)
    url = f"http://127.0.0.1:{port}"
    try:
        for _ in range(600):
            try:
                if httpx.get(url + "/health").status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        http = httpx.Client(base_url=url, timeout=60)
        body = {"model": model, "support": np.asarray(support).tolist()}
        sid = http.post("/sessions", json=body).json()["session"]
        frames = [json.dumps({"points": c.tolist()}) for c in clouds]
        hdr = {"content-type": "application/json"}

        def run(k: int, into: list, solve: list) -> None:
            for i in range(k):
                t0 = time.perf_counter()
                r = http.post(f"/sessions/{sid}/frames", content=frames[i % len(frames)], headers=hdr)
                into.append(1e3 * (time.perf_counter() - t0))
                solve.append(r.json()["timing_ms"]["solve"])

        run(5, [], [])
        alone, watched, s_alone, s_watched = [], [], [], []
        ws_url = url.replace("http://", "ws://") + f"/sessions/{sid}/watch"
        for _ in range(blocks):
            run(10, alone, s_alone)
            proc = subprocess.Popen(
                [sys.executable, "-c", watchers, ws_url, "3"],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                text=True,
            )
            proc.stdout.readline()
            time.sleep(0.3)
            run(10, watched, s_watched)
            proc.kill()
            proc.wait()
    finally:
        server.terminate()
        server.wait(10)
    return {
        "frames_each": len(alone),
        "round_trip_ms_alone": float(np.median(alone)),
        "round_trip_ms_watched": float(np.median(watched)),
        "ratio": float(np.median(watched) / np.median(alone)),
        "server_solve_ms_alone": float(np.median(s_alone)),
        "server_solve_ms_watched": float(np.median(s_watched)),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="beam")
    ap.add_argument("--store", default=str(ROOT / "model_store"))
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--frames", type=int, default=40)
    args = ap.parse_args()

    from clients import Client
    from service.api.server import BackgroundServer
    from service.bench.machine import describe
    from service.config import Settings

    machine = describe()  # before this run rewrites its own artefacts (the commit stays clean)
    out = ROOT / "reports/frontends"
    out.mkdir(parents=True, exist_ok=True)
    with BackgroundServer(Settings(store=args.store)) as server:
        with Client(server.url) as api:
            seq = api._call("GET", f"/models/{args.model}/demo?frames=20&points=500")
        clouds = [np.asarray(c, np.float64) for c in seq["clouds"]]
        clouds = clouds + clouds[::-1][1:-1]  # ping-pong, as the viewer's demo plays it
        support = seq["support"]
        viewer = _watch_10hz(server.url, args.model, clouds, support, args.seconds)
        bridge = _bridge_vs_ws(server.url, args.model, clouds, support, args.frames)
    watchers = _watchers_cost(args.store, args.model, clouds, support)
    report = {
        "machine": machine,
        "model": args.model,
        "command": " ".join(sys.argv),
        "load_average": list(os.getloadavg()),  # this machine is shared: read the figures with it
        "viewer_watching_10hz": viewer,
        "bridge_vs_websocket": bridge,
        "three_watchers_vs_none": watchers,
    }
    (out / "frontends.json").write_text(json.dumps(report, indent=2))
    print(json.dumps({k: report[k] for k in list(report)[3:]}, indent=2))
    return 0


if __name__ == "__main__":
    threading.excepthook = lambda a: None
    sys.exit(main())

"""The bridge's memory for one large cloud: the peak of Python's traced allocations (numpy's
included) while the bridge reads, checks and decodes a POLYDATA or POINT message, as a multiple
of the message's body. The API takes only small clouds here (max_points), so the cloud is
answered with the bridge's own 413 and the figure is the bridge's alone.

    python benchmarks/igtl_memory.py [--points 2000000] [--model beam] [--store model_store]
        [--repeat 3] [--untraced]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import socket
import sys
import threading
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.api.server import BackgroundServer
from service.config import Settings
from service.igtl import protocol as p
from service.igtl.bridge import Bridge, serve


def messages(n: int, version: int) -> dict[str, bytes]:
    """A points-only POLYDATA and a POINT message of ``n`` points, named ``cloud``."""
    pts = np.random.default_rng(0).random((n, 3), np.float32)
    items = np.zeros((n, p.POINT_ITEM), np.uint8)
    items[:, 100:112] = pts.astype(">f4").view(np.uint8).reshape(-1, 12)
    return {
        "POLYDATA": p.pack("POLYDATA", "cloud", p.encode_polydata(pts, np.zeros((0, 3), int)), version=version),
        "POINT": p.pack("POINT", "cloud", items.tobytes(), version=version),
    }


def _exactly(sock: socket.socket, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("closed")
        buf += chunk
    return bytes(buf)


def peak(port: int, message: bytes) -> tuple[float, float]:
    """(peak traced bytes above the start, seconds to its answer) for one message."""
    with socket.create_connection(("127.0.0.1", port), timeout=120) as sock:
        time.sleep(0.3)  # the session opened: its allocations are not the message's
        base = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        t0 = time.perf_counter()
        sock.sendall(message)
        version, mtype, device, ts, size, crc = p.parse_header(_exactly(sock, p.HEADER_SIZE))
        status = json.loads(
            p.decode_string(p.parse_body(version, mtype, device, ts, _exactly(sock, size), crc).content)
        )
        seconds = time.perf_counter() - t0
        assert status.get("error", {}).get("code") == 413, status
        return tracemalloc.get_traced_memory()[1] - base, seconds


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=2_000_000)
    ap.add_argument("--model", default="beam")
    ap.add_argument("--store", default=str(ROOT / "model_store"))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--untraced", action="store_true", help="times only: tracemalloc slows each allocation")
    args = ap.parse_args()
    api = BackgroundServer(Settings(store=args.store, max_points=1000, blas_threads=0)).start()
    ready = threading.Event()
    port: list[int] = []

    def bound(number: int) -> None:
        port.append(number)
        ready.set()

    def run() -> None:
        asyncio.run(serve(Bridge(api.url, args.model), "127.0.0.1", 0, bound))

    threading.Thread(target=run, daemon=True).start()
    ready.wait(60)
    if not args.untraced:
        tracemalloc.start()
    out = {}
    for version in (1, 2):
        for kind, message in messages(args.points, version).items():
            body = len(message) - p.HEADER_SIZE
            runs = [peak(port[0], message) for _ in range(args.repeat)]
            top = min(r[0] for r in runs)
            out[f"{kind} v{version}"] = {
                "body_MB": body / 1e6,
                "peak_MB": top / 1e6,
                "peak_over_body": top / body,
                "ms": 1e3 * min(r[1] for r in runs),
            }
            print(
                f"{kind:8s} v{version}: body {body / 1e6:7.1f} MB, peak {top / 1e6:7.1f} MB ({top / body:.2f}x), "
                f"{1e3 * min(r[1] for r in runs):.2f} ms"
            )
    api.stop()


if __name__ == "__main__":
    main()

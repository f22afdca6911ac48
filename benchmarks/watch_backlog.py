"""Stale frames a slow watcher is served before the newest (docs/frontends.md, "Watching a
session"): two watchers of one session read nothing while its frames are solved, then take one
frame per 0.1 s; one acknowledges each frame (the client library's watch), the other never
does and gets what its socket buffers hold first.

    python benchmarks/watch_backlog.py [--model phantom] [--store model_store] [--frames 80]

Prints, for each watcher, the frames it got before the newest and how long it took to reach it.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

READ_S = 0.1  # the slow watcher's time per frame


def _drain(recv, newest: int) -> tuple[list[int], float]:
    """(seqs received until the newest, seconds it took), one frame per READ_S."""
    seqs: list[int] = []
    t0 = time.perf_counter()
    while not seqs or seqs[-1] < newest:
        seqs.append(recv())
        time.sleep(READ_S)
    return seqs, time.perf_counter() - t0 - READ_S


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="phantom")
    parser.add_argument("--store", default=str(ROOT / "model_store"))
    parser.add_argument("--frames", type=int, default=80)
    parser.add_argument("--points", type=int, default=300)
    args = parser.parse_args()

    import httpx
    from websockets.sync.client import connect

    from clients import Client
    from service.api.server import BackgroundServer
    from service.bench.machine import describe
    from service.config import Settings
    from service.synthetic import sample_surface

    settings = Settings(store=args.store, max_points=3000, solver_threads=1)
    server = BackgroundServer(settings).start()
    try:
        with Client(server.url, encoding="json") as api, httpx.Client(base_url=server.url, timeout=60) as http:
            mesh = api.mesh(args.model)
            rng = np.random.default_rng(0)
            clouds = [sample_surface(mesh["nodes"], mesh["surface_faces"], args.points, rng)[0] for _ in range(4)]
            sid = http.post("/sessions", json={"model": args.model}).json()["session"]
            url = server.url.replace("http://", "ws://") + f"/sessions/{sid}/watch"
            with connect(url, max_queue=1) as plain, api.watch(sid) as acking:
                plain.recv(timeout=30)  # the hello
                t0 = time.perf_counter()
                for i in range(args.frames):
                    body = {"points": clouds[i % len(clouds)].tolist()}
                    assert http.post(f"/sessions/{sid}/frames", json=body).status_code == 200
                posted = time.perf_counter() - t0
                rows = {
                    "no acks": _drain(lambda: json.loads(plain.recv(timeout=30))["seq"], args.frames),
                    "acks": _drain(lambda: acking.recv(timeout=30)["seq"], args.frames),
                }
    finally:
        server.stop()
    machine = describe()
    print(f"{machine.get('cpu')}, commit {machine.get('commit')}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    print(f"{args.frames} frames of {args.model} ({args.points} points) posted in {posted:.1f} s")
    for name, (seqs, seconds) in rows.items():
        print(f"  {name:8s}: {len(seqs) - 1} stale frames before the newest, {seconds:.1f} s to reach it")


if __name__ == "__main__":
    main()

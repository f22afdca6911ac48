"""What the network API costs, and what it sustains.

    python benchmarks/api_bench.py --store model_store --model phantom           # full
    python benchmarks/api_bench.py --store /tmp/store_phantom --quick             # minutes
    python benchmarks/api_bench.py --parts overhead --runs 5                      # the overhead, 5 times

1. Overhead: a 1,000-point frame through the API (HTTP and WebSocket, MessagePack and JSON)
   against the same frame in-process (``Session.frame``), the same session config, the same
   cloud repeated (warm-started, so each repeat is a short, steady solve). Two figures per row:
   the median of (round trip - the server's own solve time) over paired frames, which is the
   overhead free of solve-time noise, and median round trip - median in-process time. With
   ``--runs N`` the section runs N times and each figure is the median of the N runs' medians.
2. Throughput: 1, 4 and 16 concurrent WebSocket streams (MessagePack) replaying frames:
   frames per second over all streams and latency percentiles (clients/loadtest.py,
   its frames from service/loadtest.py).
3. Memory: the server's RSS after warm-up, every 2,000 of 10,000 frames, and every 200 of 1,000
   sessions opened and dropped (half HTTP, closed with DELETE; half WebSocket, the socket dropped).

The server runs as its own process (``elastreg serve``), so its RSS is its own and the client's
work does not share its interpreter. The JSON names the machine and the commit it ran on.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench_server import start_server

from clients.client import AsyncClient, Client
from clients.loadtest import run_load
from service.bench.machine import describe
from service.loadtest import make_frames
from service.optional import need


def rss_mb(pid: int) -> float:
    psutil = need("psutil", "the API benchmark's memory figures")
    return psutil.Process(pid).memory_info().rss / 2**20


def median(x) -> float:
    return float(np.median(x))


# -- 1. overhead ----------------------------------------------------------------------------------


def in_process(store: Path, model: str, support, cloud, repeats: int) -> np.ndarray:
    from threadpoolctl import threadpool_limits

    from service.registration.session import Session, SessionConfig
    from service.store import load_entry

    entry = load_entry(store / model)
    session = Session(entry.network, SessionConfig(support=tuple(int(i) for i in support)))
    times = []
    with threadpool_limits(1):  # as the server runs its solves (blas_threads = 1)
        for i in range(repeats + 5):
            t0 = time.perf_counter()
            session.frame(cloud)
            if i >= 5:
                times.append(1e3 * (time.perf_counter() - t0))
    return np.asarray(times)


def through_api(url: str, model: str, support, cloud, repeats: int, transport: str, encoding: str):
    rtt, solve = [], []
    with Client(url, encoding=encoding) as api:
        if transport == "http":
            session = api.open_session(model, support=support)
            call, close = session.frame, session.close
        else:
            stream = api.stream(model, support=support)
            call, close = stream.frame, stream.close
        for i in range(repeats + 5):
            t0 = time.perf_counter()
            r = call(cloud)
            if i >= 5:
                rtt.append(1e3 * (time.perf_counter() - t0))
                solve.append(r["timing_ms"]["total"])
        close()
    return np.asarray(rtt), np.asarray(solve)


def overhead(url, store, model, support, cloud, repeats) -> list[dict]:
    base = in_process(store, model, support, cloud, repeats)
    rows = [{"path": "in-process Session.frame", "median_ms": round(median(base), 3)}]
    for transport in ("http", "ws"):
        for encoding in ("msgpack", "json"):
            rtt, solve = through_api(url, model, support, cloud, repeats, transport, encoding)
            rows.append(
                {
                    "path": f"{transport} {encoding}",
                    "median_ms": round(median(rtt), 3),
                    "server_solve_ms": round(median(solve), 3),
                    "overhead_paired_ms": round(median(rtt - solve), 3),
                    "overhead_vs_in_process_ms": round(median(rtt) - median(base), 3),
                }
            )
    return rows


# -- 3. memory ------------------------------------------------------------------------------------


async def many_frames(url, model, support, clouds, total: int, streams: int = 4) -> int:
    async with AsyncClient(url) as api:
        opened = [await api.stream(model, support=support) for _ in range(streams)]
        per = total // streams

        async def go(i, st):
            for k in range(per):
                await st.frame(clouds[(i + k) % len(clouds)])

        await asyncio.gather(*(go(i, st) for i, st in enumerate(opened)))
        for st in opened:
            await st.close()
    return per * streams


async def churn_sessions(url, model, support, cloud, total: int) -> None:
    async with AsyncClient(url) as api:
        for k in range(total):
            if k % 2:
                s = await api.open_session(model, support=support)
                await s.frame(cloud)
                await s.close()
            else:
                st = await api.stream(model, support=support)
                await st.send(cloud)  # dropped with its frame in flight
                await st.ws.close()


PARTS = ("overhead", "throughput", "memory")


def memory(url, pid, model, support, clouds, n_frames: int, n_sessions: int) -> dict:
    """The server's RSS after warm-up, after each fifth of the frames, then of the sessions."""
    mem = {"after_warmup_mb": rss_mb(pid)}
    t0 = time.perf_counter()
    done = 0
    for _ in range(5):
        done += asyncio.run(many_frames(url, model, support, clouds, n_frames // 5))
        mem[f"after_{done}_frames_mb"] = rss_mb(pid)
    mem["frames_seconds"] = time.perf_counter() - t0
    for step in range(1, 6):
        asyncio.run(churn_sessions(url, model, support, clouds[0], n_sessions // 5))
        time.sleep(1.0)
        mem[f"after_{step * (n_sessions // 5)}_sessions_mb"] = rss_mb(pid)
    with Client(url) as api:
        mem["open_sessions_after"] = api.health()["sessions"]["open"]
    return {k: round(v, 1) if isinstance(v, float) else v for k, v in mem.items()}


def median_rows(runs: list[list[dict]]) -> list[dict]:
    """Per path, the median over runs of each figure."""
    out = []
    for rows in zip(*runs, strict=True):
        merged = {"path": rows[0]["path"]}
        for key in rows[0]:
            if key != "path":
                merged[key] = round(median([r[key] for r in rows]), 3)
        out.append(merged)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--store", default=str(ROOT / "model_store"))
    p.add_argument("--model", default="phantom")
    p.add_argument("--quick", action="store_true", help="smaller counts and shorter runs")
    p.add_argument("--threads", type=int, default=2, help="the server's solver threads")
    p.add_argument("--points", type=int, default=1000)
    p.add_argument("--out", default=None, help="also write the figures as JSON here")
    p.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS), help="sections to run (default: all)")
    p.add_argument("--runs", type=int, default=1, help="times to run the overhead section (the median is reported)")
    args = p.parse_args(argv)
    store = Path(args.store)
    repeats, seconds = (40, 5.0) if args.quick else (200, 20.0)
    n_frames, n_sessions = (1000, 200) if args.quick else (10_000, 1000)

    proc, url, _ = start_server(
        store, {"ELASTREG_SOLVER_THREADS": str(args.threads), "ELASTREG_MAX_SESSIONS": "64"}, "bench"
    )
    report: dict = {
        "started": time.strftime("%Y-%m-%d %H:%M:%S"),
        "machine": describe(),
        "model": args.model,
        "points": args.points,
        "quick": args.quick,
        "solver_threads": args.threads,
        "parts": args.parts,
        "runs": args.runs,
        "load_average_at_start": os.getloadavg(),
    }  # others' work on the machine skews every figure
    m = report["machine"]
    print(
        f"{report['started']} on {m['cpu']}, {m['cores']} cores; commit {m['commit']}; "
        f"load average {report['load_average_at_start'][0]:.1f}"
    )
    try:

        async def frames():
            async with AsyncClient(url) as api:
                return await make_frames(api, args.model, n_points=args.points)

        clouds, support = asyncio.run(frames())
        print(f"server {url} (pid {proc.pid}); model {args.model}; {args.points} points; support {support.size} nodes")

        runs = []
        for k in range(args.runs if "overhead" in args.parts else 0):
            rows = overhead(url, store, args.model, support, clouds[-1], repeats)
            runs.append(rows)
            print(f"\n1. API overhead, {args.points}-point frame, median of {repeats} (ms), run {k + 1} of {args.runs}")
            print(f"{'path':<26}{'round trip':>11}{'solve':>8}{'overhead':>10}{'vs in-proc':>12}")
            for r in rows:
                print(
                    f"{r['path']:<26}{r['median_ms']:>11.2f}{r.get('server_solve_ms', float('nan')):>8.2f}"
                    f"{r.get('overhead_paired_ms', float('nan')):>10.2f}"
                    f"{r.get('overhead_vs_in_process_ms', float('nan')):>12.2f}"
                )
        if runs:
            report["overhead"] = median_rows(runs) if len(runs) > 1 else runs[0]
            if len(runs) > 1:
                report["overhead_runs"] = runs
                print(f"\n   median of the {len(runs)} runs (ms)")
                for r in report["overhead"]:
                    print(
                        f"{r['path']:<26}{r['median_ms']:>11.2f}{r.get('server_solve_ms', float('nan')):>8.2f}"
                        f"{r.get('overhead_paired_ms', float('nan')):>10.2f}"
                        f"{r.get('overhead_vs_in_process_ms', float('nan')):>12.2f}"
                    )

        if "throughput" in args.parts:
            print(f"\n2. concurrent WebSocket streams (msgpack), {seconds:g} s each")
            report["throughput"] = []
            for n in (1, 4, 16):
                load = asyncio.run(
                    run_load(url, args.model, streams=n, seconds=seconds, frames=clouds, support=support)
                )
                report["throughput"].append(load.as_dict())
                print("  " + load.text())

        if "memory" in args.parts:
            report["memory"] = memory(url, proc.pid, args.model, support, clouds, n_frames, n_sessions)
            print("\n3. server memory (RSS), sampled in five steps of frames, then of sessions")
            for k, v in report["memory"].items():
                print(f"  {k}: {v}")
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

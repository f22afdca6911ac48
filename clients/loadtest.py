"""A local load test: N concurrent WebSocket streams replay frames for T seconds.

    python -m clients.loadtest --url http://127.0.0.1:8000 --model phantom --streams 4 --seconds 10

Each stream keeps one frame in flight (send, wait for the result, send the next), as an AR
display does; the report gives frames per second over all streams, latency percentiles (client
round trip) and the number of errors. It is bounded on purpose: at most 64 streams, at most
600 s, and only against a loopback address (it is a tool for one's own machine, not for
loading someone else's server).
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import ipaddress
import sys
import time
from urllib.parse import urlsplit

import numpy as np

from .client import AsyncClient, StreamError

MAX_STREAMS = 64
MAX_SECONDS = 600.0


def check_target(url: str, streams: int, seconds: float) -> None:
    """Refuse what this tool must not do (ValueError): too many streams, too long, not loopback."""
    if not 1 <= streams <= MAX_STREAMS:
        raise ValueError(f"streams must lie in 1..{MAX_STREAMS}, got {streams}")
    if not 0 < seconds <= MAX_SECONDS:
        raise ValueError(f"seconds must lie in (0, {MAX_SECONDS:g}], got {seconds}")
    parts = urlsplit(url)
    host = parts.hostname or ""
    if parts.scheme not in ("http", "https"):
        raise ValueError(f"the URL must be http:// or https://, got {url!r}")
    if host != "localhost":
        try:
            loopback = ipaddress.ip_address(host).is_loopback
        except ValueError:
            loopback = False
        if not loopback:
            raise ValueError(
                f"the load test only runs against loopback addresses (127.0.0.1, ::1, localhost), not {host!r}"
            )


@dataclasses.dataclass
class LoadReport:
    streams: int
    seconds: float
    frames: int
    errors: int
    latency_ms: np.ndarray  # (frames,) client round trips
    solve_ms: np.ndarray  # (frames,) the server's solve time (timing_ms.total)
    per_stream: list[int]

    @property
    def fps(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else 0.0

    def percentile(self, q: float) -> float:
        return float(np.percentile(self.latency_ms, q)) if self.latency_ms.size else float("nan")

    def as_dict(self) -> dict:
        return {
            "streams": self.streams, "seconds": round(self.seconds, 3), "frames": self.frames,
            "fps": round(self.fps, 2), "p50_ms": round(self.percentile(50), 2),
            "p95_ms": round(self.percentile(95), 2), "p99_ms": round(self.percentile(99), 2),
            "solve_p50_ms": round(float(np.median(self.solve_ms)), 2) if self.solve_ms.size else None,
            "errors": self.errors,
        }

    def text(self) -> str:
        d = self.as_dict()
        return (f"{d['streams']} stream(s), {d['seconds']:.1f} s: {d['frames']} frames, {d['fps']:.1f} frames/s; "
                f"latency p50 {d['p50_ms']:.1f} ms, p95 {d['p95_ms']:.1f} ms, p99 {d['p99_ms']:.1f} ms "
                f"(server solve p50 {d['solve_p50_ms']} ms); errors {d['errors']}")


async def make_frames(api: AsyncClient, model: str, *, n_frames: int = 8, n_points: int = 1000,
                      seed: int = 0) -> tuple[list[np.ndarray], np.ndarray]:
    """Clouds to replay, and the support to register them with: the network's displacement
    under a growing pull on a patch (``/simulate``), sampled on the deformed surface."""
    from service.mesh import TetMesh
    from service.synthetic import sample_surface

    from .demo import PEAK_FRACTION, _patches

    m = await api.mesh(model)
    summary = await api.model(model)
    mesh = TetMesh(m["nodes"], m["tets"], m["fixed_nodes"])
    tool, support = _patches(mesh, m["region_nodes"])
    peak = PEAK_FRACTION * float(summary["training"].get("load_distribution", {}).get("max_force", 1.0))
    normal = mesh.vertex_normals[tool].sum(axis=0)
    normal /= np.linalg.norm(normal)
    rng = np.random.default_rng(seed)
    clouds = []
    for t in range(n_frames):
        g = np.tile(normal * peak * (t + 1) / n_frames / tool.size, (tool.size, 1))
        u = (await api.simulate(model, tool, g, method="network"))["displacement"]
        pts, _, _ = sample_surface(mesh.nodes + u, mesh.surface_faces, n_points, rng)
        clouds.append(pts)
    return clouds, support


async def run_load(url: str, model: str = "phantom", *, streams: int = 4, seconds: float = 10.0,
                   encoding: str = "msgpack", method: str = "network", frames: list[np.ndarray] | None = None,
                   support: np.ndarray | None = None, n_points: int = 1000, warmup: int = 1) -> LoadReport:
    """Run the load test (bounded: see :func:`check_target`) and return its report."""
    check_target(url, streams, seconds)
    async with AsyncClient(url, encoding=encoding) as api:
        if frames is None:
            frames, support = await make_frames(api, model, n_points=n_points)
        config = {"method": method}
        if support is not None:
            config["support"] = support
        opened = [await api.stream(model, **config) for _ in range(streams)]
        latency: list[list[float]] = [[] for _ in range(streams)]
        solve: list[list[float]] = [[] for _ in range(streams)]
        errors = [0] * streams

        async def one(i: int, stream, t_end: float) -> None:
            k = i  # streams start at different frames
            for _ in range(warmup):
                await stream.frame(frames[k % len(frames)])
            while time.perf_counter() < t_end:
                t0 = time.perf_counter()
                try:
                    r = await stream.frame(frames[k % len(frames)], frame_id=k)
                except StreamError:
                    errors[i] += 1
                else:
                    latency[i].append(1e3 * (time.perf_counter() - t0))
                    solve[i].append(float(r["timing_ms"]["total"]))
                k += 1

        try:
            t_start = time.perf_counter()
            await asyncio.gather(*(one(i, s, t_start + seconds) for i, s in enumerate(opened)))
            elapsed = time.perf_counter() - t_start
        finally:
            for s in opened:
                await s.close()
    return LoadReport(
        streams=streams,
        seconds=elapsed,
        frames=sum(len(x) for x in latency),
        errors=sum(errors),
        latency_ms=np.concatenate([np.asarray(x) for x in latency]),
        solve_ms=np.concatenate([np.asarray(x) for x in solve]),
        per_stream=[len(x) for x in latency],
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m clients.loadtest", description=__doc__.split("\n\n")[0])
    p.add_argument("--url", default="http://127.0.0.1:8000", help="a loopback server (default %(default)s)")
    p.add_argument("--model", default="phantom")
    p.add_argument("--streams", type=int, default=4, help=f"concurrent streams (1..{MAX_STREAMS})")
    p.add_argument("--seconds", type=float, default=10.0, help=f"duration (at most {MAX_SECONDS:g})")
    p.add_argument("--encoding", choices=["msgpack", "json"], default="msgpack")
    p.add_argument("--method", choices=["network", "fem"], default="network")
    p.add_argument("--points", type=int, default=1000, help="points per frame")
    args = p.parse_args(argv)
    try:
        check_target(args.url, args.streams, args.seconds)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    report = asyncio.run(run_load(args.url, args.model, streams=args.streams, seconds=args.seconds,
                                  encoding=args.encoding, method=args.method, n_points=args.points))
    print(report.text())
    return 0 if report.errors == 0 else 1


if __name__ == "__main__":
    sys.exit(main())

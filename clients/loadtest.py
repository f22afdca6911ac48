"""A local load test: N concurrent WebSocket streams replay frames for T seconds.

    python -m service.loadtest --url http://127.0.0.1:8000 --model phantom --streams 4 --seconds 10

(``service/loadtest.py`` makes the frames from the served model's mesh and runs :func:`run_load`.)

Each stream keeps one frame in flight (send, wait for the result, send the next), as an AR
display does; the report gives frames per second over all streams, latency percentiles (client
round trip) and the number of errors. It is bounded on purpose: at most 64 streams, at most
600 s, and only against a loopback address (it is a tool for one's own machine, not for
loading someone else's server).
"""

from __future__ import annotations

import asyncio
import dataclasses
import ipaddress
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
            "streams": self.streams,
            "seconds": round(self.seconds, 3),
            "frames": self.frames,
            "fps": round(self.fps, 2),
            "p50_ms": round(self.percentile(50), 2),
            "p95_ms": round(self.percentile(95), 2),
            "p99_ms": round(self.percentile(99), 2),
            "solve_p50_ms": round(float(np.median(self.solve_ms)), 2) if self.solve_ms.size else None,
            "errors": self.errors,
        }

    def text(self) -> str:
        d = self.as_dict()
        return (
            f"{d['streams']} stream(s), {d['seconds']:.1f} s: {d['frames']} frames, {d['fps']:.1f} frames/s; "
            f"latency p50 {d['p50_ms']:.1f} ms, p95 {d['p95_ms']:.1f} ms, p99 {d['p99_ms']:.1f} ms "
            f"(server solve p50 {d['solve_p50_ms']} ms); errors {d['errors']}"
        )


async def run_load(
    url: str,
    model: str = "phantom",
    *,
    frames: list[np.ndarray],
    support: np.ndarray | None = None,
    streams: int = 4,
    seconds: float = 10.0,
    encoding: str = "msgpack",
    method: str = "network",
    warmup: int = 1,
    token: str | None = None,
) -> LoadReport:
    """Replay `frames` (clouds, (m, 3) each) over `streams` streams for `seconds`, bounded (see
    :func:`check_target`), and return the report; ``token`` for a server with tokens.
    ``service/loadtest.py`` makes frames for a served model and runs this from the command line."""
    if not frames:
        raise ValueError("the load test needs frames to replay")
    check_target(url, streams, seconds)
    async with AsyncClient(url, encoding=encoding, token=token) as api:
        config = {"method": method}
        if support is not None:
            config["support"] = support
        opened: list = []
        try:  # every stream opened is closed, even when a later one is refused
            for _ in range(streams):
                opened.append(await api.stream(model, **config))
        except BaseException:
            for s in opened:
                await s.close()
            raise
        latency: list[list[float]] = [[] for _ in range(streams)]
        solve: list[list[float]] = [[] for _ in range(streams)]
        errors = [0] * streams

        async def warm(i: int, stream) -> None:
            for _ in range(warmup):
                await stream.frame(frames[i % len(frames)])

        async def one(i: int, stream, t_end: float) -> None:
            k = i  # streams start at different frames
            while time.perf_counter() < t_end:
                t0 = time.perf_counter()
                try:
                    r = await stream.frame(frames[k % len(frames)], frame_id=k)
                except StreamError as exc:
                    if exc.close_code is not None:  # the server closed the stream: the run ends
                        raise
                    errors[i] += 1  # an error message: the stream goes on
                else:
                    latency[i].append(1e3 * (time.perf_counter() - t0))
                    solve[i].append(float(r["timing_ms"]["total"]))
                k += 1

        try:  # the clock starts once every stream is warm: a cold first frame is not load
            await asyncio.gather(*(warm(i, s) for i, s in enumerate(opened)))
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

"""A local load test: N concurrent WebSocket streams replay frames for T seconds.

    python -m service.loadtest --url http://127.0.0.1:8000 --model phantom --streams 4 --seconds 10

(``service/loadtest.py`` makes the frames from the served model's mesh and runs :func:`run_load`.)

Each stream keeps one frame in flight (send, wait for the result, send the next), as an AR
display does; the report gives frames per second over all streams, latency percentiles (client
round trip), the frames the server refused at capacity (a 503: the stream waits its
``retry_after`` before its next try), the frames left unanswered and the other errors. It is
bounded on purpose: at most 64 streams, at most 600 s, and only against a loopback address (it
is a tool for one's own machine, not for loading someone else's server). A run ends at most
:data:`REPLY_GRACE_S` after its seconds even when the server stops answering (frozen).
"""

from __future__ import annotations

import asyncio
import dataclasses
import ipaddress
import time
from collections.abc import Callable
from urllib.parse import urlsplit

import numpy as np

from .client import AsyncClient, StreamError

MAX_STREAMS = 64
MAX_SECONDS = 600.0
#: how long past its seconds a run waits for the frames still in flight: a frame unanswered by
#: then (a frozen server) counts as unanswered, and its stream sends no more
REPLY_GRACE_S = 5.0
#: the wait after a 503 that named none (the server's always name one: API.md)
DEFAULT_RETRY_S = 1.0


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
    refused: int = 0  # frames the server refused at capacity (503), each retried after retry_after
    unanswered: int = 0  # frames with no reply by the run's end and its grace (a frozen server)

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
            "refused": self.refused,
            "unanswered": self.unanswered,
            "errors": self.errors,
        }

    def text(self) -> str:
        d = self.as_dict()
        latency = (
            f"latency p50 {d['p50_ms']:.1f} ms, p95 {d['p95_ms']:.1f} ms, p99 {d['p99_ms']:.1f} ms "
            f"(server solve p50 {d['solve_p50_ms']} ms)"
            if self.frames
            else "no latency measured"
        )
        return (
            f"{d['streams']} stream(s), {d['seconds']:.1f} s: {d['frames']} frames, {d['fps']:.1f} frames/s; "
            f"{latency}; refused at capacity {d['refused']}; unanswered {d['unanswered']}; errors {d['errors']}"
        )


class Tally:
    """A run's figures as they are measured: a caller that hands :func:`run_load` its own still
    has them (:meth:`report`) when the run ends early (Ctrl-C, a stream the server closed)."""

    def __init__(self, on_start: Callable[[], None] | None = None) -> None:
        self.on_start = on_start  # called as the clock starts
        self._clear(0)
        self.started: float | None = None  # not yet: the clock starts once every stream is warm

    def _clear(self, streams: int) -> None:
        self.streams = streams
        self.latency: list[list[float]] = [[] for _ in range(streams)]
        self.solve: list[list[float]] = [[] for _ in range(streams)]
        self.errors = [0] * streams
        self.refused = [0] * streams
        self.unanswered = 0
        self.stopped: float | None = None

    def start(self, streams: int) -> None:
        """Start the clock, for `streams` streams, with nothing measured."""
        self._clear(streams)
        self.started = time.perf_counter()
        if self.on_start is not None:
            self.on_start()

    def stop(self) -> None:
        if self.stopped is None:
            self.stopped = time.perf_counter()

    def report(self) -> LoadReport:
        """The figures so far (those of the whole run once it ended)."""
        end = self.stopped if self.stopped is not None else time.perf_counter()
        return LoadReport(
            streams=self.streams,
            seconds=end - self.started if self.started is not None else 0.0,
            frames=sum(len(x) for x in self.latency),
            errors=sum(self.errors),
            latency_ms=np.concatenate([np.asarray(x) for x in self.latency]) if self.latency else np.empty(0),
            solve_ms=np.concatenate([np.asarray(x) for x in self.solve]) if self.solve else np.empty(0),
            per_stream=[len(x) for x in self.latency],
            refused=sum(self.refused),
            unanswered=self.unanswered,
        )


async def _wait_to_retry(exc: StreamError, until: float) -> None:
    """Wait the ``retry_after`` of a refusal at capacity (a 503), but not past ``until``."""
    wait = exc.retry_after if exc.retry_after is not None else DEFAULT_RETRY_S
    await asyncio.sleep(max(0.0, min(wait, until - time.perf_counter())))


def _abandon(stream) -> None:
    """Close an unanswered stream without waiting for the closing handshake (websockets'
    close_timeout, 10 s): a server that left a frame unanswered will not answer its close."""
    stream.ws.close_timeout = 0


def _quit(exc: BaseException, streams: list) -> None:
    """A run left by Ctrl-C (the task cancelled) or by a server that stopped answering closes
    its streams the quick way, as :func:`_abandon` does: each close would otherwise wait 10 s."""
    if isinstance(exc, (TimeoutError, asyncio.CancelledError, KeyboardInterrupt)):
        for stream in streams:
            _abandon(stream)


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
    max_error: float | None = None,
    warmup: int = 1,
    token: str | None = None,
    tally: Tally | None = None,
) -> LoadReport:
    """Replay `frames` (clouds, (m, 3) each) over `streams` streams for `seconds`, bounded (see
    :func:`check_target`), and return the report; ``token`` for a server with tokens,
    ``max_error`` (metres) for method auto, ``tally`` to keep the figures of a run ended early.
    A stream the server closed ends the run (its StreamError raised). ``service/loadtest.py``
    makes frames for a served model and runs this from the command line."""
    if not frames:
        raise ValueError("the load test needs frames to replay")
    check_target(url, streams, seconds)
    tally = tally if tally is not None else Tally()
    async with AsyncClient(url, encoding=encoding, token=token) as api:
        config: dict = {"method": method}
        if max_error is not None:
            config["max_error"] = max_error
        if support is not None:
            config["support"] = support
        ready_by = time.perf_counter() + seconds  # refused opens and warm-up frames are retried until then

        async def open_one():
            while True:
                try:  # bounded as a frame is: a server frozen before measuring ends the run too
                    return await asyncio.wait_for(
                        api.stream(model, **config), ready_by + REPLY_GRACE_S - time.perf_counter()
                    )
                except TimeoutError:
                    raise TimeoutError(
                        f"no stream opened within {seconds + REPLY_GRACE_S:g} s (--seconds and grace)"
                    ) from None
                except StreamError as exc:  # a 503 (no thread to build the session now): try later
                    if exc.status != 503 or time.perf_counter() >= ready_by:
                        raise
                    await _wait_to_retry(exc, ready_by)

        opened: list = []
        try:  # every stream opened is closed, even when a later one is refused
            for _ in range(streams):
                opened.append(await open_one())
        except BaseException as exc:
            _quit(exc, opened)
            await asyncio.gather(*(s.close() for s in opened), return_exceptions=True)
            raise

        async def warm(i: int, stream, t_end: float) -> bool:
            """Whether the stream is fit to measure: not when a warm-up frame went unanswered."""
            for _ in range(warmup):
                while True:
                    t0 = time.perf_counter()
                    try:
                        await asyncio.wait_for(
                            stream.frame(frames[i % len(frames)]), max(t_end, t0) + REPLY_GRACE_S - t0
                        )
                        break
                    except TimeoutError:
                        _abandon(stream)
                        return False
                    except StreamError as exc:
                        if exc.status != 503:
                            raise
                        if t0 >= t_end:  # refused until t_end: the stream runs cold
                            return True
                        await _wait_to_retry(exc, t_end)
            return True

        async def one(i: int, stream, t_end: float) -> None:
            k = i  # streams start at different frames
            while (t0 := time.perf_counter()) < t_end:
                try:
                    r = await asyncio.wait_for(
                        stream.frame(frames[k % len(frames)], frame_id=k), t_end + REPLY_GRACE_S - t0
                    )
                except TimeoutError:  # no reply by the run's end and its grace: the stream is out of step
                    tally.unanswered += 1
                    _abandon(stream)
                    return
                except StreamError as exc:
                    if exc.close_code is not None:  # the server closed the stream: the run ends
                        raise
                    if exc.status == 503:
                        tally.refused[i] += 1
                        await _wait_to_retry(exc, t_end)
                    else:
                        tally.errors[i] += 1  # an error message: the stream goes on
                else:
                    tally.latency[i].append(1e3 * (time.perf_counter() - t0))
                    tally.solve[i].append(float(r["timing_ms"]["total"]))
                k += 1

        try:  # the clock starts once every stream is warm (or opening and warm-up took the run's seconds)
            fit = await asyncio.gather(*(warm(i, s, ready_by) for i, s in enumerate(opened)))
            tally.start(streams)
            tally.unanswered = fit.count(False)
            t_end = time.perf_counter() + seconds
            await asyncio.gather(*(one(i, s, t_end) for i, s in enumerate(opened) if fit[i]))
        except BaseException as exc:
            _quit(exc, opened)
            raise
        finally:
            tally.stop()
            await asyncio.gather(*(s.close() for s in opened), return_exceptions=True)
    return tally.report()

"""Abuse benchmark: do four well-behaved streams keep their latency while other clients misbehave?

    python benchmarks/abuse_bench.py                       # about 2 minutes
    python benchmarks/abuse_bench.py --seconds 20 --out /tmp/abuse.json

The server runs as its own process (``elastreg serve`` on a free loopback port, the shipped
``phantom`` model, tokens on, every other setting at its default), so its RSS is its own. Four
WebSocket streams send 1,000-point frames at 10 Hz (each waits for its result) for ``--seconds``
alone, then for ``--seconds`` again while other clients, on the same machine, send:

- decoding bombs: 4 MiB MessagePack bodies of empty lists, and JSON bodies of ``[],`` repeated;
- idle sockets (a handshake, then nothing) and slow ones (an HTTP body at one byte a second;
  streams that send frames and never read the replies);
- oversized bodies and WebSocket messages, and garbage frames (random bytes, text);
- open/close storms (streams and HTTP sessions opened and closed in a loop), and requests
  without a token;
- one stuck stream: a raw socket that opens a session, sends a frame, then neither reads nor
  answers pings. The time until the server has dropped its session is reported.

It prints the good streams' p50/p99 latency with and without the abuse and their ratio (same
run), the server's peak RSS and its growth, the count of 5xx answers (500s and 503s apart), and
writes a JSON artefact naming the machine and the commit. Bounded on purpose: loopback only,
at most 60 s a phase, a fixed number of misbehaving clients, each at a fixed rate.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import collections
import json
import multiprocessing
import secrets
import sys
import threading
import time
from pathlib import Path

import httpx
import msgpack
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench_server import start_server

from clients.client import AsyncClient, StreamError
from service.loadtest import make_frames

HOST = "127.0.0.1"
MAX_SECONDS = 60.0
GOOD_STREAMS = 4
RATE_HZ = 10.0


class RssSampler:
    """The server's resident memory, sampled every 50 ms from a thread."""

    def __init__(self, pid: int) -> None:
        import psutil

        self.proc = psutil.Process(pid)
        self.peak = 0.0
        self.samples: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                mb = self.proc.memory_info().rss / 2**20
            except Exception:
                return
            self.samples.append((time.monotonic(), mb))
            self.peak = max(self.peak, mb)
            time.sleep(0.05)

    def now(self) -> float:
        return self.proc.memory_info().rss / 2**20

    def __enter__(self) -> RssSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


class Tally:
    """Every answer the clients saw, by kind and status."""

    def __init__(self) -> None:
        self.counts: collections.Counter = collections.Counter()

    def http(self, what: str, status: int) -> None:
        self.counts[f"{what} {status}"] += 1

    def ws(self, what: str, code) -> None:
        self.counts[f"{what} ws:{code}"] += 1

    def server_errors(self) -> dict[str, int]:
        """HTTP 5xx answers and stream errors with a 5xx code; close code 1011 (internal error)."""
        out = {"500": 0, "503": 0, "other_5xx": 0, "ws_close_1011": 0}
        for key, n in self.counts.items():
            status = key.rsplit(" ", 1)[1]
            if status == "ws:1011":
                out["ws_close_1011"] += n
                continue
            if status.startswith("ws:"):
                if not status.startswith("ws:error:"):
                    continue  # a close code (1008, 1009...): not an HTTP status
                status = status.removeprefix("ws:error:")
            if status.isdigit() and 500 <= int(status) < 600:
                out["500" if status == "500" else "503" if status == "503" else "other_5xx"] += n
        return out


# -- the well-behaved streams -----------------------------------------------------------------------


async def good_streams(url: str, token: str, frames, support, seconds: float, tally: Tally) -> list[float]:
    """Four streams at 10 Hz, each frame's round trip (ms)."""
    latencies: list[float] = []

    async def one(i: int) -> None:
        async with AsyncClient(url, token=token) as api:
            stream = await api.stream("phantom", support=support)
            try:
                for k in range(3):  # warm-up, not timed
                    await stream.frame(frames[(i + k) % len(frames)])
                t_next = time.perf_counter()
                t_end = t_next + seconds
                k = i
                while t_next < t_end:
                    t0 = time.perf_counter()
                    try:
                        await stream.frame(frames[k % len(frames)], frame_id=k)
                        latencies.append(1e3 * (time.perf_counter() - t0))
                    except StreamError as err:
                        if err.close_code is not None:  # the server closed this stream: it is over
                            tally.ws("good", err.close_code)  # tallied as the abusive sockets' codes
                            return
                        tally.ws("good", f"error:{err.status}")
                    k += 1
                    t_next += 1.0 / RATE_HZ
                    await asyncio.sleep(max(0.0, t_next - time.perf_counter()))
            finally:
                await stream.close()

    await asyncio.gather(*(one(i) for i in range(GOOD_STREAMS)))
    return latencies


# -- the misbehaving clients ----------------------------------------------------------------------


def _mask(payload: bytes, opcode: int) -> bytes:
    """One masked WebSocket frame (what a client sends), written by hand."""
    key = secrets.token_bytes(4)
    n = len(payload)
    head = bytes([0x80 | opcode])
    if n < 126:
        head += bytes([0x80 | n])
    elif n < 1 << 16:
        head += bytes([0x80 | 126]) + n.to_bytes(2, "big")
    else:
        head += bytes([0x80 | 127]) + n.to_bytes(8, "big")
    masked = (
        bytes(b ^ key[i % 4] for i, b in enumerate(payload))
        if n < 4096
        else (np.frombuffer(payload, np.uint8) ^ np.resize(np.frombuffer(key, np.uint8), n)).tobytes()
    )
    return head + key + masked


async def raw_websocket(url: str, token: str | None):
    """A WebSocket handshake over a plain socket: (reader, writer) after the 101."""
    port = int(url.rsplit(":", 1)[1])
    reader, writer = await asyncio.open_connection(HOST, port)
    key = base64.b64encode(secrets.token_bytes(16)).decode()
    auth = f"Authorization: Bearer {token}\r\n" if token else ""
    writer.write(
        (
            f"GET /stream HTTP/1.1\r\nHost: {HOST}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n{auth}\r\n"
        ).encode()
    )
    await writer.drain()
    head = await reader.readuntil(b"\r\n\r\n")
    if b" 101 " not in head.split(b"\r\n", 1)[0]:
        writer.close()
        raise ConnectionError(head.split(b"\r\n", 1)[0].decode())
    return reader, writer


async def _read_frame(reader) -> tuple[int, bytes]:
    """(opcode, payload) of the next (unfragmented, unmasked) server frame."""
    b0, b1 = await reader.readexactly(2)
    n = b1 & 0x7F
    if n == 126:
        n = int.from_bytes(await reader.readexactly(2), "big")
    elif n == 127:
        n = int.from_bytes(await reader.readexactly(8), "big")
    return b0 & 0x0F, await reader.readexactly(n)


async def _read_ws_message(reader) -> bytes:
    """The payload of the next data message (pings are skipped, and never answered)."""
    while True:
        opcode, payload = await _read_frame(reader)
        if opcode in (0x1, 0x2):
            return payload
        if opcode == 0x8:
            raise ConnectionError(f"closed {int.from_bytes(payload[:2], 'big') if len(payload) >= 2 else ''}")


async def _close_code(reader, timeout: float):
    """The code of the server's close frame (pings skipped, never answered)."""

    async def wait():
        while True:
            opcode, payload = await _read_frame(reader)
            if opcode == 0x8:
                return int.from_bytes(payload[:2], "big") if len(payload) >= 2 else "none"

    try:
        return await asyncio.wait_for(wait(), timeout)
    except (TimeoutError, asyncio.IncompleteReadError, ConnectionError):
        return "dropped"


async def stuck_stream(url: str, token: str, frame: bytes, result: dict) -> None:
    """Open a session, send a frame, then never read or answer a ping: how long until the
    server has dropped the session?"""
    reader, writer = await raw_websocket(url, token)
    writer.write(_mask(json.dumps({"model": "phantom"}).encode(), 0x1))
    await writer.drain()
    sid = json.loads(await _read_ws_message(reader))["session"]
    writer.write(_mask(frame, 0x2))
    await writer.drain()
    t0 = time.monotonic()
    async with httpx.AsyncClient(base_url=url, headers={"authorization": f"Bearer {token}"}) as c:
        while time.monotonic() - t0 < 120:
            r = await c.get(f"/sessions/{sid}")
            if r.status_code == 404:
                result["reclaimed_s"] = time.monotonic() - t0
                break
            await asyncio.sleep(0.25)
    writer.close()


async def abuse(
    url: str, token: str, frame_msgpack: bytes, stop: asyncio.Event, tally: Tally, limits: dict, stuck: dict
) -> None:
    auth = {"authorization": f"Bearer {token}"}
    mp_headers = {**auth, "content-type": "application/msgpack"}
    bomb_mp = b"\xdd" + (4 << 20).to_bytes(4, "big") + b"\x90" * (4 << 20)
    bomb_json = b'{"points": [' + b"[]," * ((4 << 20) // 3) + b"[]]}"

    async with httpx.AsyncClient(base_url=url, timeout=60) as c:
        sid = (await c.post("/sessions", json={"model": "phantom"}, headers=auth)).json()["session"]

        async def every(period: float, fn) -> None:
            while not stop.is_set():
                t0 = time.monotonic()
                try:
                    await fn()
                except Exception as exc:
                    tally.counts[f"{fn.__name__} ended by {type(exc).__name__}"] += 1
                await asyncio.sleep(max(0.0, period - (time.monotonic() - t0)))

        async def bombs() -> None:
            r = await c.post(f"/sessions/{sid}/frames", content=bomb_mp, headers=mp_headers)
            tally.http("msgpack bomb", r.status_code)
            r = await c.post(
                f"/sessions/{sid}/frames", content=bomb_json, headers={**auth, "content-type": "application/json"}
            )
            tally.http("json bomb", r.status_code)

        async def oversized() -> None:
            big = b"\x00" * (limits["max_body_bytes"] + 1)
            r = await c.post(f"/sessions/{sid}/frames", content=big, headers=mp_headers)
            tally.http("oversized body", r.status_code)
            reader, writer = await raw_websocket(url, token)
            writer.write(_mask(b"\x00" * (limits["max_message_bytes"] + 1), 0x2))
            try:
                await writer.drain()
            except ConnectionError:
                pass
            tally.ws("oversized message", await _close_code(reader, 10))
            writer.close()

        async def garbage() -> None:
            r = await c.post(f"/sessions/{sid}/frames", content=secrets.token_bytes(512), headers=mp_headers)
            tally.http("garbage body", r.status_code)
            r = await c.post(
                f"/sessions/{sid}/frames",
                content=b'{"points": [[1, 2',
                headers={**auth, "content-type": "application/json"},
            )
            tally.http("garbage body", r.status_code)
            r = await c.post(
                "/sessions", content=b'{"model": "phantom"}', headers={**auth, "content-type": "text/plain"}
            )
            tally.http("text/plain body", r.status_code)

        async def garbage_stream() -> None:
            from websockets.asyncio.client import connect

            async with connect(url.replace("http", "ws") + "/stream", additional_headers=auth) as ws:
                await ws.send(json.dumps({"model": "phantom"}))
                await ws.recv()
                for _ in range(25):
                    await ws.send(secrets.token_bytes(256) if secrets.randbits(1) else "not json {[")
                    reply = await ws.recv()  # in the message's own kind: MessagePack for bytes
                    reply = msgpack.unpackb(reply) if isinstance(reply, bytes) else json.loads(reply)
                    tally.ws("garbage frame", f"error:{reply['error']['code']}")
                    await asyncio.sleep(0.2)

        async def storm() -> None:
            from websockets.asyncio.client import connect

            async with connect(url.replace("http", "ws") + "/stream", additional_headers=auth) as ws:
                await ws.send(json.dumps({"model": "phantom"}))
                reply = json.loads(await ws.recv())
                tally.ws("storm stream", "opened" if "session" in reply else reply["error"]["code"])
            r = await c.post("/sessions", json={"model": "phantom"}, headers=auth)
            tally.http("storm session", r.status_code)
            if r.status_code == 201:
                tally.http(
                    "storm close", (await c.delete(f"/sessions/{r.json()['session']}", headers=auth)).status_code
                )
            tally.http("no token", (await c.post("/sessions", json={"model": "phantom"})).status_code)

        async def idle_socket() -> None:
            reader, writer = await raw_websocket(url, None)  # then nothing: closed after first_message_timeout_s
            try:
                tally.ws("idle socket", await _close_code(reader, 60))
            finally:
                writer.close()

        async def slow_body() -> None:
            port = int(url.rsplit(":", 1)[1])
            reader, writer = await asyncio.open_connection(HOST, port)
            writer.write(
                (
                    f"POST /sessions HTTP/1.1\r\nHost: {HOST}:{port}\r\nAuthorization: Bearer {token}\r\n"
                    "Content-Type: application/json\r\nContent-Length: 1000\r\n\r\n"
                ).encode()
            )
            await writer.drain()
            t0 = time.monotonic()
            status = None
            while status is None and time.monotonic() - t0 < 60 and not stop.is_set():
                writer.write(b" ")  # one byte a second
                await writer.drain()
                try:
                    line = await asyncio.wait_for(reader.readline(), 1.0)
                    status = int(line.split()[1]) if line else "closed"
                except TimeoutError:
                    pass
            tally.http("slow body", status or "unfinished")
            writer.close()

        async def unread_stream() -> None:
            reader, writer = await raw_websocket(url, token)
            try:
                writer.write(_mask(json.dumps({"model": "phantom"}).encode(), 0x1))
                await writer.drain()
                await _read_ws_message(reader)
                for _ in range(30):  # a frame a second, its results never read
                    writer.write(_mask(frame_msgpack, 0x2))
                    await writer.drain()
                    await asyncio.sleep(1.0)
                    if stop.is_set():
                        break
            finally:
                writer.close()

        tasks = [
            every(1.0, bombs),
            every(2.0, oversized),
            every(0.5, garbage),
            every(0.0, garbage_stream),
            every(0.5, storm),
            every(0.5, slow_body),
            every(0.5, slow_body),
            every(0.0, unread_stream),
            every(0.0, unread_stream),
        ]
        tasks += [every(0.0, idle_socket) for _ in range(16)]
        runners = [asyncio.create_task(t) for t in tasks]
        stuck_task = asyncio.create_task(stuck_stream(url, token, frame_msgpack, stuck))
        await stop.wait()
        for t in runners:
            t.cancel()
        await asyncio.gather(*runners, return_exceptions=True)
        await asyncio.wait_for(stuck_task, 130)


def abuse_process(url: str, token: str, frame_msgpack: bytes, limits: dict, stop, results) -> None:
    """The misbehaving clients in a process of their own: their work (building bombs, masking
    16 MiB messages) never stalls the good streams' event loop."""

    async def main() -> None:
        tally, stuck, done = Tally(), {}, asyncio.Event()

        async def watch() -> None:
            while not stop.is_set():
                await asyncio.sleep(0.05)
            done.set()

        watcher = asyncio.create_task(watch())
        await abuse(url, token, frame_msgpack, done, tally, limits, stuck)
        watcher.cancel()
        results.put({"counts": dict(tally.counts), "stuck": stuck})

    asyncio.run(main())


# -- the run --------------------------------------------------------------------------------------


def pct(x, q) -> float:
    return float(np.percentile(x, q)) if len(x) else float("nan")


async def run(url: str, token: str, seconds: float, sampler: RssSampler) -> dict:
    from clients.client import encode

    async with AsyncClient(url, token=token) as api:
        frames, support = await make_frames(api, "phantom", n_points=1000)
        limits = (await api.health())["limits"]
    frame_msgpack = encode({"points": frames[0]}, "msgpack")
    tally_alone, tally = Tally(), Tally()
    alone = await good_streams(url, token, frames, support, seconds, tally_alone)
    rss_before = sampler.now()
    peak_before = sampler.peak
    ctx = multiprocessing.get_context("spawn")
    stop, results = ctx.Event(), ctx.Queue()
    abusers = ctx.Process(target=abuse_process, args=(url, token, frame_msgpack, limits, stop, results))
    abusers.start()
    await asyncio.sleep(5.0)  # the abuse under way before the good streams are timed again
    together = await good_streams(url, token, frames, support, seconds, tally)
    stop.set()
    abused = await asyncio.to_thread(results.get, True, 180)
    abusers.join(timeout=30)
    tally.counts.update(abused["counts"])
    stuck = abused["stuck"]
    async with httpx.AsyncClient(base_url=url) as c:
        health = (await c.get("/health")).json()
    return {
        "alone": {"frames": len(alone), "p50_ms": pct(alone, 50), "p99_ms": pct(alone, 99)},
        "abused": {"frames": len(together), "p50_ms": pct(together, 50), "p99_ms": pct(together, 99)},
        "ratio_p50": pct(together, 50) / pct(alone, 50),
        "ratio_p99": pct(together, 99) / pct(alone, 99),
        "expected_frames": int(GOOD_STREAMS * RATE_HZ * seconds),
        "rss_mb": {
            "before_abuse": rss_before,
            "peak_before_abuse": peak_before,
            "peak": sampler.peak,
            "growth": sampler.peak - rss_before,
        },
        "server_errors": tally.server_errors(),
        "server_errors_alone": tally_alone.server_errors(),
        "stuck_session_reclaimed_s": stuck.get("reclaimed_s"),
        "answers": dict(sorted(tally.counts.items())),
        "health_after": health,
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--store", default=str(ROOT / "model_store"), help="a store with the phantom model")
    p.add_argument("--seconds", type=float, default=30.0, help=f"each phase (at most {MAX_SECONDS:g})")
    p.add_argument("--out", default=str(ROOT / "reports" / "abuse" / "abuse.json"))
    args = p.parse_args(argv)
    if not 0 < args.seconds <= MAX_SECONDS:
        p.error(f"--seconds must lie in (0, {MAX_SECONDS:g}]")
    from service.bench.machine import describe

    token = secrets.token_urlsafe(24)
    proc, url, log = start_server(Path(args.store), {"ELASTREG_API_TOKENS": token}, "abuse")
    try:
        with RssSampler(proc.pid) as sampler:
            result = asyncio.run(run(url, token, args.seconds, sampler))
    finally:
        proc.terminate()
        proc.wait(timeout=60)
    out = {
        "benchmark": "abuse",
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": describe(),
        "command": "python benchmarks/abuse_bench.py " + " ".join(argv or sys.argv[1:]),
        "seconds_per_phase": args.seconds,
        "good_streams": GOOD_STREAMS,
        "rate_hz": RATE_HZ,
        "server_settings": "defaults, with ELASTREG_API_TOKENS set",
        **result,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1, default=float) + "\n")
    a, b = result["alone"], result["abused"]
    print(f"machine: {out['machine']['cpu']}, commit {out['machine']['commit']}")
    print(f"good streams alone:  {a['frames']} frames, p50 {a['p50_ms']:.1f} ms, p99 {a['p99_ms']:.1f} ms")
    print(
        f"good streams abused: {b['frames']} frames, p50 {b['p50_ms']:.1f} ms, p99 {b['p99_ms']:.1f} ms "
        f"(ratio p50 {result['ratio_p50']:.2f}, p99 {result['ratio_p99']:.2f}; aim p99 within 2x)"
    )
    r = result["rss_mb"]
    print(
        f"server RSS: {r['before_abuse']:.0f} MB before the abuse, peak {r['peak']:.0f} MB "
        f"(growth {r['growth']:.0f} MB; aim under 200)"
    )
    print(f"5xx answers under abuse: {result['server_errors']} (alone: {result['server_errors_alone']})")
    print(f"stuck session reclaimed after {result['stuck_session_reclaimed_s']} s")
    print(f"wrote {args.out} (server log: {log})")
    return 0


if __name__ == "__main__":
    sys.exit(main())

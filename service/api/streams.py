"""A registration stream over one WebSocket: its session lives and dies with the connection.

Protocol (API.md): the first message is a session config, answered ``{"session", "config"}``;
then one frame per message, one result per frame, in order. Binary messages are MessagePack
and text messages JSON; each reply comes in its message's kind. A bad frame (undecodable,
invalid, refused by the engine, too many points) is answered ``{"error": {"code", "detail"}}``
in its turn and the stream goes on with its state unchanged; only a bad first message closes
the socket (1008), and a full server closes it with 1013 (try again later).

Two tasks per stream: a reader that queues messages as they arrive (bounded: a client that
outruns the server is slowed by TCP, not by our memory) and a worker that answers them in
order, each solve in the pool. With ``skip_stale`` the worker takes everything queued when it
becomes free, answers the bad ones, solves only the newest good frame and reports the frames it
skipped (``skipped``, ``skipped_ids``); a support sent with a skipped frame still applies.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time

from fastapi import WebSocket
from starlette.websockets import WebSocketState

from . import codec
from .errors import ApiError, as_api_error
from .schemas import FrameIn, SessionCreate, check_points_limit
from .sessions import RegistryFull
from .work import not_found_model, open_session, opened, solve_frame

log = logging.getLogger(__name__)

POLICY = 1008  # a bad first message
TRY_LATER = 1013  # the server is at its session limit
_THREAD_DECODE = 256 << 10  # messages larger than this are decoded off the event loop
_CLOSED = object()
_IDLE = object()


def _reason(text: str) -> str:
    """A close reason fits in 123 bytes of UTF-8."""
    b = text.encode()[:120]
    return b.decode(errors="ignore")


class StreamRunner:
    """Runs one WebSocket stream to its end (never raises for a client's mistakes)."""

    def __init__(self, ws: WebSocket) -> None:
        state = ws.app.state
        self.ws = ws
        self.settings = state.settings
        self.models = state.models
        self.registry = state.registry
        self.pool = state.pool
        self.held = None
        self.busy = False

    # -- sending -----------------------------------------------------------------------------------

    async def _send(self, kind: str, body: bytes) -> bool:
        try:
            if kind == codec.MSGPACK:
                await self.ws.send_bytes(body)
            else:
                await self.ws.send_text(body.decode())
            return True
        except Exception:  # the client went away mid-reply
            return False

    async def _error(self, kind: str, err: ApiError, frame_id=None) -> bool:
        body = {"code": err.status, "detail": err.text}
        if frame_id is not None:
            body["frame_id"] = frame_id
        return await self._send(kind, codec.encode({"error": body}, kind))

    async def _close(self, code: int, reason: str) -> None:
        if self.ws.client_state == WebSocketState.CONNECTED:
            try:
                await self.ws.close(code, _reason(reason))
            except Exception:
                pass

    async def _receive(self, timeout: float | None):
        """(kind, data) of the next message, _CLOSED when the client has gone, _IDLE on timeout."""
        try:
            msg = await asyncio.wait_for(self.ws.receive(), timeout)
        except TimeoutError:
            return _IDLE
        except Exception:
            return _CLOSED
        if msg["type"] == "websocket.disconnect":
            return _CLOSED
        if msg.get("bytes") is not None:
            return codec.MSGPACK, msg["bytes"], time.perf_counter()
        return codec.JSON, msg.get("text") or "", time.perf_counter()

    # -- the stream --------------------------------------------------------------------------------

    async def run(self) -> None:
        await self.ws.accept(headers=[(b"x-elastreg-instance", self.settings.instance_id.encode())])
        first = await self._receive(self.settings.session_ttl_s)
        if first is _CLOSED:
            return
        if first is _IDLE:
            await self._close(1000, "no session config within the idle timeout")
            return
        try:
            if await self._open(*first[:2]):
                await self._frames()
        finally:
            if self.held is not None:  # opened (even if the client left before the reply)
                self.registry.close(self.held.id, why="ended with its WebSocket stream")

    async def _open(self, kind: str, data) -> bool:
        try:
            obj = codec.decode(data, kind, max_bytes=self.settings.max_body_bytes)
            if not isinstance(obj, dict):
                raise ApiError(422, "the first message must be a session config (a map)")
            create = SessionCreate.model_validate(obj)
            entry = self.models.get(create.model)
            if entry is None:
                raise not_found_model(create.model, self.models)
            self.held = await open_session(entry, create, kind="stream", registry=self.registry, pool=self.pool)
        except RegistryFull as exc:
            await self._error(kind, ApiError(503, str(exc)))
            await self._close(TRY_LATER, "server at its session limit")
            return False
        except Exception as exc:
            err = as_api_error(exc)
            if err is None:
                log.error("opening a stream failed", exc_info=exc)
                err = ApiError(500, f"internal error ({type(exc).__name__}); it has been logged")
            await self._error(kind, err)
            await self._close(POLICY, err.text)
            return False
        reply = opened(self.held, self.settings.instance_id)
        return await self._send(kind, codec.encode(reply, kind))

    async def _frames(self) -> None:
        queue: asyncio.Queue = asyncio.Queue(maxsize=self.settings.stream_queue)
        reader = asyncio.create_task(self._read(queue))
        try:
            while True:
                item = await queue.get()
                if item is _CLOSED:
                    return
                if item is _IDLE:
                    await self._close(1000, f"idle for {self.settings.session_ttl_s:g} s")
                    return
                batch = [item]
                closing = False
                if self.held.skip_stale:
                    while not queue.empty():
                        nxt = queue.get_nowait()
                        if nxt is _CLOSED or nxt is _IDLE:
                            closing = True
                            break
                        batch.append(nxt)
                if not await self._answer(batch) or closing:
                    return
        finally:
            reader.cancel()
            await self._close(1000, "")

    async def _read(self, queue: asyncio.Queue) -> None:
        ttl = self.settings.session_ttl_s
        while True:
            item = await self._receive(ttl)
            if item is _IDLE and (self.busy or not queue.empty()):
                continue
            await queue.put(item)
            if item is _CLOSED or item is _IDLE:
                return

    def _parse(self, kind: str, data) -> FrameIn:
        obj = codec.decode(data, kind, max_bytes=self.settings.max_body_bytes)
        if not isinstance(obj, dict):
            raise ApiError(422, "a frame must be a map with points (and optionally support, frame_id)")
        check_points_limit(obj, self.settings.max_points)
        return FrameIn.model_validate(obj)

    async def _answer(self, batch: list) -> bool:
        """Answer a batch (one message, or all queued ones with skip_stale); False when the
        client has gone."""
        good = []
        for kind, data, t_received in batch:
            t0 = time.perf_counter()
            try:
                if len(data) > _THREAD_DECODE:  # a large JSON cloud takes a while to parse
                    frame = await asyncio.to_thread(self._parse, kind, data)
                else:
                    frame = self._parse(kind, data)
            except Exception as exc:
                err = as_api_error(exc) or ApiError(500, f"internal error ({type(exc).__name__})")
                if err.status == 500:
                    log.error("decoding a frame failed", exc_info=exc)
                if not await self._error(kind, err, _frame_id(data, kind)):
                    return False
                continue
            good.append((kind, frame, t_received, 1e3 * (time.perf_counter() - t0)))
        if not good:
            return True
        kind, frame, t_received, decode_ms = good[-1]
        extra, support = None, None
        if self.held.skip_stale:
            skipped = [f for _, f, _, _ in good[:-1]]
            extra = {"skipped": len(skipped), "skipped_ids": [f.frame_id for f in skipped]}
            if frame.support is None:  # a support sent with a skipped frame still applies
                support = next((f.support for f in reversed(skipped) if f.support is not None), None)
        self.busy = True
        try:
            body = await self.pool.run(
                solve_frame, self.held, frame, kind, {"decode": decode_ms},
                t_received=t_received, t_submitted=time.perf_counter(), support=support, extra=extra,
            )
        except Exception as exc:
            err = as_api_error(exc)
            if err is None:
                log.error("a stream frame failed", exc_info=exc)
                err = ApiError(500, f"internal error ({type(exc).__name__}); it has been logged")
            return await self._error(kind, err, frame.frame_id)
        finally:
            self.busy = False
        return await self._send(kind, body)


def _frame_id(data, kind: str):
    """The frame_id of an undecodable or invalid frame, when one can be read (else None); JSON
    is read leniently here (NaN literals allowed) since only the id is wanted."""
    try:
        obj = json.loads(data) if kind == codec.JSON else codec.decode(data, kind)
    except Exception:
        return None
    fid = obj.get("frame_id") if isinstance(obj, dict) else None
    if isinstance(fid, str) and len(fid) <= 256:
        return fid
    if isinstance(fid, int) and not isinstance(fid, bool) and -(2**63) <= fid < 2**63:
        return fid
    return None

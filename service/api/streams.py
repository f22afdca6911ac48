"""A registration stream over one WebSocket: its session lives and dies with the connection.

Protocol (API.md): the first message is a session config, answered ``{"session", "config"}``;
then one frame per message, one result per frame, in order. Binary messages are MessagePack
and text messages JSON; each reply comes in its message's kind. A bad frame (undecodable,
invalid, refused by the engine, too many points) is answered ``{"error": {"code", "detail"}}``
in its turn and the stream goes on with its state unchanged; only a bad first message closes
the socket (1008), and a full server closes it with 1013 (try again later). Every 503 error
carries ``retry_after``, the seconds to wait (an HTTP 503's ``Retry-After``).

Two tasks per stream: a reader that queues messages as they arrive (bounded in messages and in
bytes: a client that outruns the server is slowed by TCP, not by our memory) and a worker that
answers them in order, each solve in the pool. With ``skip_stale`` the worker takes everything
queued when it becomes free, answers the bad ones, solves only the newest good frame and reports
the frames it skipped (``skipped``, ``skipped_ids``); a support sent with a skipped frame still
applies.

Access and limits (API.md, "Access"): the socket counts against ``max_sockets``, or while it
waits for its first message's token ``max_tokenless_sockets`` (:mod:`.sockets`; a handshake over
either is answered 503); the token comes in the handshake or the first message
(:func:`~.deps.authorize_websocket`), else the socket closes with 1008; a first message must
come within ``first_message_timeout_s``. A frame that finds the solve pool saturated gets a 503
error of its own and the stream goes on. Frames still queued when the client leaves are
dropped, not solved; a client that takes nothing of its replies for ``send_timeout_s``, or
takes them more slowly than ``send_min_bytes_per_s``, ends the stream (:mod:`.wsend`). When
the server shuts down, the frame being solved is answered, the queued ones get a 503, and the
socket closes with 1012 (service restart).
"""

from __future__ import annotations

import asyncio
import json
import logging
import time

from fastapi import WebSocket

from ..sendwait import Stalled
from . import codec
from .errors import ApiError, as_api_error, unprocessable
from .schemas.common import check_points_limit
from .schemas.sessions import FrameIn, SessionCreate
from .sockets import Slot, websocket_slot
from .work import Dropped, check_frame_support, not_found_model, open_session, opened, solve_frame
from .wsend import close, send_message

log = logging.getLogger(__name__)

POLICY = 1008  # a bad first message, or no valid token
TRY_LATER = 1013  # a 503 for the first message: the session limit, or no thread to open it now
RESTART = 1012  # the server is shutting down
_THREAD_DECODE = 256 << 10  # messages larger than this are decoded off the event loop
_LENIENT_ID = 64 << 10  # an undecodable message is read again for its frame_id up to this size
_CLOSED = object()
_IDLE = object()
_DRAIN = object()


class StreamRunner:
    """Runs one WebSocket stream to its end (never raises for a client's mistakes)."""

    def __init__(self, ws: WebSocket) -> None:
        state = ws.app.state
        self.ws = ws
        self.settings = state.settings
        self.models = state.models
        self.registry = state.registry
        self.pool = state.pool
        self.slot: Slot | None = None  # its place among the open sockets (run)
        self.held = None
        self.busy = False
        self.gone = False  # the client has left: queued frames are dropped
        self._left = asyncio.Event()  # set with gone (the reader saw the socket close)
        self.draining = False
        self.queue: asyncio.Queue | None = None
        self.queued_bytes = 0
        self._space = asyncio.Event()

    # -- sending -----------------------------------------------------------------------------------

    async def _send(self, kind: str, body: bytes) -> bool:
        """False when the client has gone, or stopped taking replies (wsend.send_message)."""
        try:
            await send_message(self.ws, body, kind == codec.MSGPACK, self.settings)
            return True
        except Stalled as exc:
            log.info("a stream's client %s: closing it", exc)
            self.gone = True
            return False
        except Exception:  # the client went away mid-reply
            self.gone = True
            return False

    async def _error(self, kind: str, err: ApiError, frame_id=None, extra: dict | None = None) -> bool:
        """An error message; `extra` names the frames skip_stale skipped for it (none was answered)."""
        body = {"code": err.status, "detail": err.text}
        if frame_id is not None:
            body["frame_id"] = frame_id
        if extra and extra.get("skipped"):
            body.update(extra)
        if err.retry_after is not None:  # a 503's Retry-After, in seconds
            body["retry_after"] = err.retry_after
        return await self._send(kind, codec.encode({"error": body}, kind))

    async def _close(self, code: int, reason: str) -> None:
        await close(self.ws, code, reason, self.settings)

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
        async with websocket_slot(self.ws) as slot:
            if slot is not None:
                self.slot = slot
                await self._run()

    async def _run(self) -> None:
        await self.ws.accept(headers=[(b"x-elastreg-instance", self.settings.instance_id.encode())])
        if "authorization" in self.ws.headers:  # a bad header token is refused now, not after a message
            try:
                self.slot.authorize()  # the verdict admission reached: no second compare
            except ApiError as err:
                await self._error(codec.JSON, err)
                await self._close(POLICY, err.text)
                return
        wait = self.settings.first_message_timeout_s
        first = await self._receive(wait)
        if first is _CLOSED:
            return
        if first is _IDLE:
            await self._close(POLICY, f"no session config within {wait:g} s")
            return
        streams = self.ws.app.state.streams
        streams.add(self)
        try:
            if await self._open(*first[:2]):
                await self._frames()
        finally:
            streams.discard(self)
            if self.held is not None:  # opened (even if the client left before the reply)
                self.registry.close(self.held.id, why="ended with its WebSocket stream")

    def drain(self) -> None:
        """The server is shutting down: answer what is queued, then close (1012)."""
        self.draining = True
        if self.queue is not None and self.queue.empty():
            self.queue.put_nowait(_DRAIN)  # wakes the worker

    def _decode(self, data, kind: str):
        return codec.decode(
            data, kind, max_bytes=self.settings.max_message_bytes, max_elements=self.settings.max_array_elements
        )

    async def _open(self, kind: str, data) -> bool:
        try:
            if len(data) > _THREAD_DECODE:
                obj = await asyncio.to_thread(self._decode, data, kind)
            else:
                obj = self._decode(data, kind)
            if not isinstance(obj, dict):
                raise ApiError(422, "the first message must be a session config (a map)")
            assert self.slot is not None
            owner = self.slot.authorize(obj)
            create = SessionCreate.model_validate(obj)
            entry = self.models.get(create.model)
            if entry is None:
                raise not_found_model(create.model, self.models)
            self.held = await open_session(
                entry,
                create,
                kind="stream",
                registry=self.registry,
                pool=self.pool,
                settings=self.settings,
                owner=owner,
            )
        except Exception as exc:
            err = as_api_error(exc)
            if err is None:
                log.error("opening a stream failed", exc_info=exc)
                err = ApiError(500, f"internal error ({type(exc).__name__}); it has been logged")
            await self._error(kind, err)
            # a 503 (the session limit, no thread to build the session now, shutting down) is
            # not the client's fault: try again later, as its error's retry_after says
            await self._close(TRY_LATER if err.status == 503 else POLICY, err.text)
            return False
        reply = opened(self.held, self.settings.instance_id)
        return await self._send(kind, codec.encode(reply, kind))

    def _taken(self, item):
        """An item leaves the queue: its bytes no longer count."""
        if isinstance(item, tuple):
            self.queued_bytes -= len(item[1])
            self._space.set()
        return item

    async def _frames(self) -> None:
        self.queue = queue = asyncio.Queue(maxsize=self.settings.stream_queue)
        self.draining = self.draining or self.pool.draining
        reader = asyncio.create_task(self._read(queue))
        code, reason = 1000, ""
        try:
            while True:
                if self.draining and queue.empty():  # what was queued is answered (503s)
                    code, reason = RESTART, "the server is shutting down"
                    return
                item = self._taken(await queue.get())
                if item is _CLOSED or self.gone:
                    return
                if item is _IDLE:
                    code, reason = 1000, f"idle for {self.settings.session_ttl_s:g} s"
                    return
                if item is _DRAIN:
                    continue
                batch = [item]
                closing = False
                if self.held.skip_stale:
                    while not queue.empty():
                        nxt = self._taken(queue.get_nowait())
                        if nxt is _DRAIN:
                            continue
                        if not isinstance(nxt, tuple):
                            closing = True
                            break
                        batch.append(nxt)
                if not await self._answer(batch) or closing:
                    return
        finally:
            reader.cancel()
            await self._close(code, reason)

    async def _read(self, queue: asyncio.Queue) -> None:
        ttl = self.settings.session_ttl_s
        limit = self.settings.stream_queue_bytes
        while True:
            item = await self._receive(ttl)
            if item is _IDLE and (self.busy or not queue.empty()):
                continue
            if item is _CLOSED:
                self.gone = True  # before it is queued: the worker drops what is still queued
                self._left.set()
            if isinstance(item, tuple):
                while self.queued_bytes and self.queued_bytes + len(item[1]) > limit:
                    self._space.clear()  # reads pause: TCP slows the client down
                    await self._space.wait()
                self.queued_bytes += len(item[1])
            await queue.put(item)
            if item is _CLOSED or item is _IDLE:
                return

    def _parse(self, kind: str, data) -> tuple[FrameIn | None, Exception | None, object]:
        """(frame, None, id) or (None, the error, the frame_id when it could be read): a refused
        frame's id comes from this one decode, never a second parse of its whole body."""
        try:
            obj = self._decode(data, kind)
        except Exception as exc:  # only a small body is read again, leniently, for its id
            return None, exc, _frame_id(data, kind) if len(data) <= _LENIENT_ID else None
        try:
            if not isinstance(obj, dict):
                raise ApiError(422, "a frame must be a map with points (and optionally support, frame_id)")
            check_points_limit(obj, self.settings.max_points)
            return FrameIn.model_validate(obj), None, None
        except Exception as exc:
            return None, exc, _id_of(obj)

    async def _answer(self, batch: list) -> bool:
        """Answer a batch (one message, or all queued ones with skip_stale); False when the
        client has gone."""
        good = []
        for kind, data, t_received in batch:
            t0 = time.perf_counter()
            if len(data) > _THREAD_DECODE:  # a large JSON cloud takes a while to parse
                frame, exc, fid = await asyncio.to_thread(self._parse, kind, data)
            else:
                frame, exc, fid = self._parse(kind, data)
            if frame is None:
                err = as_api_error(exc) or ApiError(500, f"internal error ({type(exc).__name__})")
                if err.status == 500:
                    log.error("decoding a frame failed", exc_info=exc)
                if not await self._error(kind, err, fid):
                    return False
                continue
            good.append((kind, frame, t_received, 1e3 * (time.perf_counter() - t0)))
        extra, support = None, None
        if self.held.skip_stale:
            # every frame's support is checked, the answered one's too: one refused is answered
            # under its own id and the newest good frame before it is answered in its place
            valid = []
            for item in good:
                f = item[1]
                try:
                    if f.support is not None:
                        check_frame_support(self.held, f.support)
                except ValueError as exc:
                    if not await self._error(item[0], unprocessable(str(exc), "support"), f.frame_id):
                        return False
                    continue
                valid.append(item)
            good = valid
            skipped = [f for _, f, _, _ in good[:-1]]
            extra = {"skipped": len(skipped), "skipped_ids": [f.frame_id for f in skipped]}
            for f in skipped:  # a support sent with a skipped frame still applies
                support = f.support if f.support is not None else support
            if good and good[-1][1].support is not None:
                support = None  # the answered frame's own
        if not good:
            return True
        kind, frame, t_received, decode_ms = good[-1]
        if self.gone:
            return False
        self.busy = True
        held, registry = self.held, self.registry
        try:
            registry.begin(held)
            solve = asyncio.ensure_future(
                self.pool.run(
                    solve_frame,
                    held,
                    frame,
                    kind,
                    {"decode": decode_ms},
                    t_received=t_received,
                    t_submitted=time.perf_counter(),
                    support=support,
                    extra=extra,
                    cancelled=lambda: self.gone,
                    done=lambda: registry.end(held),
                )
            )
            left = asyncio.ensure_future(self._left.wait())
            await asyncio.wait({solve, left}, return_when=asyncio.FIRST_COMPLETED)
            left.cancel()
            if not solve.done():  # the client left: the stream ends now; the job, dropped or
                # finishing, keeps its session's slot until it is over (registry.end)
                solve.add_done_callback(lambda f: f.cancelled() or f.exception())
                return False
            body = solve.result()
        except Dropped:
            return False
        except Exception as exc:
            err = as_api_error(exc)
            if err is None:
                log.error("a stream frame failed", exc_info=exc)
                err = ApiError(500, f"internal error ({type(exc).__name__}); it has been logged")
            return await self._error(kind, err, frame.frame_id, extra)
        finally:
            self.busy = False
        return await self._send(kind, body)


def _frame_id(data, kind: str):
    """The frame_id of a small undecodable frame, when one can be read (else None); JSON is
    read leniently here (NaN literals allowed) since only the id is wanted."""
    try:
        obj = json.loads(data) if kind == codec.JSON else codec.decode(data, kind, max_bytes=_LENIENT_ID)
    except Exception:
        return None
    return _id_of(obj)


def _id_of(obj):
    """A decoded frame's frame_id, when it is one the reply can carry (else None)."""
    fid = obj.get("frame_id") if isinstance(obj, dict) else None
    if isinstance(fid, str) and len(fid) <= 256:
        return fid
    if isinstance(fid, int) and not isinstance(fid, bool) and -(2**63) <= fid < 2**63:
        return fid
    return None

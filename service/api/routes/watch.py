"""``WS /sessions/{id}/watch``: an observer of a session (a second screen, the viewer).

Protocol: connect (``?encoding=msgpack`` for binary MessagePack messages; JSON text otherwise),
optionally sending a first message ``{"token": ...}``. The server answers ``{"watching": id,
"model", "config"}``, then one message per frame the session solves: ``{"seq", "time",
"points", "result"}`` (``result`` as the session's own client received it). A watcher that
falls behind gets the newest frame next; the frames it missed are the gaps in ``seq``. When the
session ends the socket is closed (1000), after the frame that was being solved then, if one
was (frames still queued are dropped unsolved); an unknown session gets ``{"error": {"code": 404}}``
and a close with 1008.

Acknowledgements (optional): a watcher may send ``{"ack": seq}`` (JSON text, or MessagePack
binary) once it has handled the frame with that ``seq``; ``{"ack": 0}`` says it will, before
any frame. From its first ack on it is sent at most :data:`~..watch.WINDOW` frames beyond the
newest it acknowledged, so one that handles frames slowly gets the newest next instead of the
frames its socket buffers hold. One whose window stays full for ``send_timeout_s`` while a
newer frame waits is closed (1008); one that takes nothing of its messages for that long, or
takes them too slowly, is dropped (:mod:`..wsend`). A message that cannot be read, or an ack
of a ``seq`` never sent, is answered ``{"error": {"code": 422, "detail"}}`` (413 over 64 KiB)
and the watcher goes on, its window as it was; any other map (a token) is ignored.
"""

from __future__ import annotations

import asyncio
import logging
import time

from fastapi import APIRouter, WebSocket
from starlette.types import Message

from ...sendwait import Stalled
from .. import codec
from ..errors import ApiError, as_api_error
from ..sessions import Held, SessionNotFound, SessionRegistry
from ..sockets import Slot, websocket_slot
from ..watch import Acks, Mailbox
from ..work import config_of
from ..wsend import close, send_message

router = APIRouter(tags=["watch"])
log = logging.getLogger(__name__)

POLICY = 1008
TRY_LATER = 1013  # no socket slot free for it now (a 503)
POLL_S = 0.25  # how often an idle watcher checks that its session and its client still exist
MAX_ACK_BYTES = 1 << 16  # an ack is a few bytes; a first message (a token) is as small


def find_session(registry: SessionRegistry, session_id: str, owner: str | None) -> Held:
    """The session to watch, looked up as the session routes do: another token's session is a
    404, like an unknown one."""
    return registry.get(session_id, touch=False, owner=owner)  # watching keeps no session alive


class Watcher:
    """Runs one watch socket to its end (never raises for a client's mistakes)."""

    def __init__(self, ws: WebSocket, session_id: str) -> None:
        self.ws = ws
        self.session_id = session_id
        self.registry: SessionRegistry = ws.app.state.registry
        self.settings = ws.app.state.settings
        enc = ws.query_params.get("encoding", "json").lower()
        self.kind = codec.MSGPACK if enc in ("msgpack", "application/msgpack") else codec.JSON
        self.acks = Acks()
        self._sending = asyncio.Lock()  # frames and error replies come from two tasks
        self._complaint: asyncio.Task | None = None  # sends the answers to bad messages
        self._unanswered: bytes | None = None  # the newest answer not sent yet

    async def _send(self, data: bytes) -> bool:
        """False when the client has gone, or stopped taking messages (wsend.send_message): a
        watcher that stops reading would otherwise hold its socket slot (and its session's
        publisher) for ever, past the session's end, as a stream's client would."""
        try:
            async with self._sending:
                await send_message(self.ws, data, self.kind == codec.MSGPACK, self.settings)
            return True
        except Stalled as exc:
            log.info("a watcher of %s %s: closing it", self.session_id, exc)
            return False
        except Exception:  # the client went away mid-message
            return False

    async def _close(self, code: int, reason: str) -> None:
        await close(self.ws, code, reason, self.settings)

    async def _refuse(self, status: int, detail: str) -> None:
        await self._send(codec.encode({"error": {"code": status, "detail": detail}}, self.kind))
        await self._close(TRY_LATER if status == 503 else POLICY, detail)

    async def _first_message(self) -> tuple[bool, dict | None]:
        """(still connected, the first message as a map, or None); a client silent past the
        timeout is refused with 1008, as /stream refuses one."""
        wait = self.settings.first_message_timeout_s
        try:
            msg = await asyncio.wait_for(self.ws.receive(), wait)
        except TimeoutError:
            await self._refuse(
                401, f"no token within {wait:g} s: send it in the first message or the Authorization header"
            )
            return False, None
        except Exception:
            return False, None
        if msg["type"] == "websocket.disconnect":
            return False, None
        try:
            obj = _decoded(msg)
        except Exception:
            obj = None
        return True, obj if isinstance(obj, dict) else None

    async def _read(self) -> None:
        """Take the client's acks (and answer bad messages) until it disconnects."""
        try:
            while True:
                msg = await self.ws.receive()
                if msg["type"] == "websocket.disconnect":
                    return
                self._take(msg)
        except Exception:  # the connection broke: the same as a disconnect
            return

    def _take(self, msg: Message) -> None:
        try:
            obj = _decoded(msg)
            if not isinstance(obj, dict):
                raise ApiError(422, 'a watcher sends maps: {"ack": seq} (or a token first)')
            if "ack" in obj:
                self.acks.ack(obj["ack"])
        except Exception as exc:  # a DecodeError, TooLarge or a refused ack
            err = as_api_error(exc) or ApiError(422, str(exc))
            self._complain(err)

    def _complain(self, err: ApiError) -> None:
        """Answer a bad message without holding up the reader (its acks open the window). While
        an answer waits for the socket, only the newest later one waits behind it: a flood of bad
        messages costs one pending answer, and a client that sends one at a time gets each."""
        log.debug("a watcher of %s sent a bad message: %s", self.session_id, err.text)
        self._unanswered = codec.encode({"error": {"code": err.status, "detail": err.text}}, self.kind)
        if self._complaint is None or self._complaint.done():
            self._complaint = asyncio.create_task(self._answer())

    async def _answer(self) -> None:
        while self._unanswered is not None:
            body, self._unanswered = self._unanswered, None
            if not await self._send(body):
                return

    async def run(self) -> None:
        async with websocket_slot(self.ws) as slot:
            if slot is not None:
                await self._run(slot)

    async def _run(self, slot: Slot) -> None:
        await self.ws.accept(headers=[(b"x-elastreg-instance", self.settings.instance_id.encode())])
        first = None
        if "authorization" not in self.ws.headers and self.settings.api_tokens:
            connected, first = await self._first_message()  # browsers send the token here
            if not connected:
                return
        try:
            owner = slot.authorize(first)
            held = find_session(self.registry, self.session_id, owner)
        except ApiError as exc:
            await self._refuse(exc.status, exc.text)
            return
        except SessionNotFound as exc:
            await self._refuse(404, str(exc))
            return
        hello = {
            "watching": held.id,
            "model": held.model,
            "config": {k: v for k, v in config_of(held).items() if k != "matching"},
        }
        if not await self._send(codec.encode(hello, self.kind)):
            return
        box = Mailbox(asyncio.get_running_loop())
        held.watch.subscribe(box)
        reader = asyncio.create_task(self._read())
        try:
            await self._forward(held, box, reader)
        finally:
            held.watch.unsubscribe(box)
            reader.cancel()
            if self._complaint is not None:
                self._complaint.cancel()
            log.debug(
                "watcher of %s: %d frames published, %d overwritten, acknowledged up to %s",
                held.id,
                box.received,
                box.overwritten,
                self.acks.acked,
            )

    async def _forward(self, held: Held, box: Mailbox, reader: asyncio.Task) -> None:
        while not reader.done():
            if self.acks.full:
                if not await self._await_ack(held, box, reader):
                    return
                continue
            item = await box.get(POLL_S)
            if item is None:
                if await self._ended(held, box):
                    return
                continue
            self.acks.sent(item.seq)  # before the send: its ack may come before the send returns
            data = await asyncio.to_thread(item.encoded, self.kind)  # off the loop, once per frame
            if not await self._send(data):
                return

    async def _await_ack(self, held: Held, box: Mailbox, reader: asyncio.Task) -> bool:
        """Wait for an ack to open the full window (frames meanwhile overwrite the mailbox);
        False when the watcher is done: it left, its session ended, or it acknowledged nothing
        for send_timeout_s while a newer frame waited."""
        since = time.monotonic()
        while self.acks.full and not reader.done():
            self.acks.freed.clear()
            try:
                await asyncio.wait_for(self.acks.freed.wait(), POLL_S)
            except TimeoutError:
                if await self._ended(held, box):
                    return False
                wait = self.settings.send_timeout_s
                if box.pending and time.monotonic() - since > wait:
                    log.info("a watcher of %s acknowledged no frame for %g s: closing it", self.session_id, wait)
                    await self._close(POLICY, f"no frame acknowledged for {wait:g} s")
                    return False
        return True

    async def _ended(self, held: Held, box: Mailbox) -> bool:
        """True, after sending the frame published last and closing the socket (1000), when the
        session has ended and no frame of it is still being solved."""
        if not held.closed or held.busy:  # a frame in flight is published before busy drops
            return False
        last = box.take()  # published just before it closed
        if last is not None:
            await self._send(await asyncio.to_thread(last.encoded, self.kind))
        await self._close(1000, "the session has ended")
        return True


def _decoded(msg: Message):
    """A client's message, decoded by its own kind (binary is MessagePack, text JSON)."""
    raw = msg.get("bytes") if msg.get("bytes") is not None else (msg.get("text") or "")
    return codec.decode(raw, codec.MSGPACK if isinstance(raw, bytes) else codec.JSON, max_bytes=MAX_ACK_BYTES)


@router.websocket("/sessions/{session_id}/watch")
async def watch(websocket: WebSocket, session_id: str) -> None:
    """Every frame the session solves (points and result); the newest first when behind."""
    await Watcher(websocket, session_id).run()

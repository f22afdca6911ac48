"""Watchers of a session: every frame the session solves goes to each of them, newest first.

Each held session has a :class:`Channel`. The solve path (a pool thread, right after a frame's
reply is encoded) calls :meth:`Channel.publish`, which only stores a reference in each watcher's
one-slot :class:`Mailbox` and wakes its task: no encoding, no waiting, no queue that grows. A
watcher that falls behind finds only the newest frame in its slot (the ones it missed show as
gaps in ``seq``). Encoding happens in the watcher's own task, off the event loop, once per frame
and encoding however many watchers there are (:meth:`Published.encoded`).

The slot drops a frame when the next comes before the watcher's task has taken it: mostly once
the watcher's socket stops taking them, which on loopback is megabytes of buffered frames later,
but also while its task still sends the frame before (late, on a loaded machine). A watcher that
acknowledges what it has handled (:class:`Acks`) is sent at most :data:`WINDOW` frames ahead of
its acknowledgements, so it skips at once.
"""

from __future__ import annotations

import asyncio
import collections
import dataclasses
import threading
import time
from typing import Any

import numpy as np

from . import codec


@dataclasses.dataclass(eq=False)
class Published:
    """One solved frame as its watchers get it: ``{"seq", "time", "points", "result"}``."""

    seq: int
    time: float  # wall clock (s) when the session published it
    points: np.ndarray  # (m, 3) the frame's cloud
    result: dict[str, Any]  # the frame result, as the session's own client received it
    _encoded: dict[str, bytes] = dataclasses.field(default_factory=dict)
    _lock: threading.Lock = dataclasses.field(default_factory=threading.Lock)

    def message(self) -> dict[str, Any]:
        return {"seq": self.seq, "time": self.time, "points": self.points, "result": self.result}

    def encoded(self, kind: str) -> bytes:
        """The message in ``kind`` (JSON or MessagePack), encoded by the first watcher to ask."""
        with self._lock:
            data = self._encoded.get(kind)
            if data is None:
                data = self._encoded[kind] = codec.encode(self.message(), kind)
            return data


class Mailbox:
    """One watcher's slot: holds the newest unread frame only. ``put`` is safe from any thread
    and never blocks on the reader; ``get`` is awaited on the watcher's event loop."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._lock = threading.Lock()
        self._item: Published | None = None
        self._ready = asyncio.Event()
        self._waking = False
        self.received = 0
        self.overwritten = 0  # frames replaced in the slot before this watcher took them

    def put(self, item: Published) -> None:
        with self._lock:
            self.received += 1
            self.overwritten += self._item is not None
            self._item = item
            wake, self._waking = not self._waking, True
        if wake:
            try:
                self._loop.call_soon_threadsafe(self._ready.set)
            except RuntimeError:  # the watcher's loop has closed: nobody to tell
                pass

    async def get(self, timeout: float | None = None) -> Published | None:
        """The newest frame, or None after ``timeout`` seconds without one."""
        try:
            await asyncio.wait_for(self._ready.wait(), timeout)
        except TimeoutError:
            return None
        return self.take()

    @property
    def pending(self) -> bool:
        """A frame waits in the slot."""
        return self._item is not None

    def take(self) -> Published | None:
        """The newest frame if one is waiting, without waiting."""
        with self._lock:
            item, self._item = self._item, None
            self._waking = False
            self._ready.clear()
        return item


WINDOW = 2  # frames an acknowledging watcher may hold unacknowledged: one being shown, one on its way


class Acks:
    """One watcher's acknowledgements, on its event loop. Until its first ack a watcher is sent
    frames without a window (as before acks existed); after it, at most :data:`WINDOW`
    frames beyond the newest it acknowledged. An ack is cumulative: ``ack(n)`` covers every frame
    sent with a ``seq`` up to ``n``; ``ack(0)`` (nothing handled yet) turns the window on before
    the first frame."""

    def __init__(self) -> None:
        self._sent: collections.deque[int] = collections.deque(maxlen=WINDOW)  # newest seqs sent
        self.acked: int | None = None  # newest seq acknowledged; None: this watcher does not ack
        self.freed = asyncio.Event()  # set when an ack opens a full window

    @property
    def full(self) -> bool:
        """No frame may be sent until an ack comes (seqs only grow: the unacked ones are the newest)."""
        return self.acked is not None and len(self._sent) == WINDOW and self._sent[0] > self.acked

    def sent(self, seq: int) -> None:
        self._sent.append(seq)

    def ack(self, seq: object) -> None:
        """Take an ack; ValueError (its text for the client) for one that is not a ``seq`` this
        watcher was sent, or 0."""
        if not isinstance(seq, int) or isinstance(seq, bool):
            raise ValueError(f"ack must be an integer seq, got {type(seq).__name__}")
        newest = self._sent[-1] if self._sent else 0
        if not 0 <= seq <= newest:
            raise ValueError(f"ack {seq} is not a frame sent to this watcher (0 to {newest})")
        self.acked = max(seq, self.acked or 0)
        if not self.full:
            self.freed.set()


class Channel:
    """A session's watchers. Thread-safe; ``seq`` counts the session's solved frames from 1."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._boxes: tuple[Mailbox, ...] = ()
        self._seq = 0

    def subscribe(self, box: Mailbox) -> None:
        with self._lock:
            self._boxes = (*self._boxes, box)

    def unsubscribe(self, box: Mailbox) -> None:
        with self._lock:
            self._boxes = tuple(b for b in self._boxes if b is not box)

    @property
    def watchers(self) -> int:
        return len(self._boxes)

    def publish(self, points: np.ndarray, payload: dict[str, Any], timing: dict[str, float]) -> None:
        """A frame was solved: hand it to every watcher (references only, no copies)."""
        with self._lock:  # frames of one session are solved one at a time; the lock is cheap
            self._seq += 1
            seq, boxes = self._seq, self._boxes
        if not boxes:
            return
        item = Published(seq, time.time(), points, {**payload, "timing_ms": dict(timing)})
        for box in boxes:
            box.put(item)

"""Watchers of a session: every frame the session solves goes to each of them, newest first.

Each held session has a :class:`Channel`. The solve path (a pool thread, right after a frame's
reply is encoded) calls :meth:`Channel.publish`, which only stores a reference in each watcher's
one-slot :class:`Mailbox` and wakes its task: no encoding, no waiting, no queue that grows. A
watcher that falls behind finds only the newest frame in its slot (the ones it missed show as
gaps in ``seq``). Encoding happens in the watcher's own task, off the event loop, once per frame
and encoding however many watchers there are (:meth:`Published.encoded`).
"""

from __future__ import annotations

import asyncio
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

    def take(self) -> Published | None:
        """The newest frame if one is waiting, without waiting."""
        with self._lock:
            item, self._item = self._item, None
            self._waking = False
            self._ready.clear()
        return item


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

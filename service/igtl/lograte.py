"""What a client's messages make the bridge log, bounded: a peer sends thousands of malformed or
unrecognised messages a second, and each would be a log line (121 bytes of log per 58-byte
message) and a remembered name. Lines past a burst per period are counted and the count is logged
once the period is over; names are remembered in an LRU of a fixed size."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import OrderedDict
from collections.abc import Hashable

#: lines a client may cause per period, and the period (s): a misconfigured sender is still seen
BURST = 20
PERIOD = 10.0
#: (type, device name) pairs remembered to log a warning the first time only: past this many the
#: least recently seen is forgotten (and warned of again if it comes back)
SEEN_KEPT = 256


class Throttle:
    """At most ``BURST`` lines per ``PERIOD`` through ``log``; the rest are counted, and their
    number is logged at WARNING when the period ends (or with the next line, off an event loop)."""

    def __init__(self, log: logging.Logger) -> None:
        self.log = log
        self._start = -float("inf")  # the current period's start (monotonic s)
        self._lines = 0  # lines logged in it
        self._suppressed = 0  # lines not logged in it
        self.suppressed_total = 0  # for tests and the curious

    def __call__(self, level: int, msg: str, *args: object) -> None:
        if not self.log.isEnabledFor(level):  # a line not logged anyway takes no one's place
            return
        now = time.monotonic()
        if now - self._start >= PERIOD:
            self._flush()
            self._start, self._lines = now, 0
        if self._lines < BURST:
            self._lines += 1
            self.log.log(level, msg, *args)
            return
        if self._suppressed == 0:  # the first suppressed of this period: its count told at its end
            with contextlib.suppress(RuntimeError):  # no running loop: told with the next line
                asyncio.get_running_loop().call_later(self._start + PERIOD - now, self._flush)
        self._suppressed += 1
        self.suppressed_total += 1

    def _flush(self) -> None:
        if self._suppressed:
            self.log.warning(
                "%d more lines about clients' messages were not logged in the last %g s (at most %d a period)",
                self._suppressed,
                PERIOD,
                BURST,
            )
            self._suppressed = 0


class Seen:
    """Whether a key was seen before, of the last ``SEEN_KEPT`` distinct keys (an LRU)."""

    def __init__(self, kept: int = SEEN_KEPT) -> None:
        self.kept = kept
        self._keys: OrderedDict[Hashable, None] = OrderedDict()

    def __len__(self) -> int:
        return len(self._keys)

    def first(self, key: Hashable) -> bool:
        """True the first time ``key`` comes (or the first since it was forgotten); it is kept."""
        if key in self._keys:
            self._keys.move_to_end(key)
            return False
        self._keys[key] = None
        if len(self._keys) > self.kept:
            self._keys.popitem(last=False)
        return True

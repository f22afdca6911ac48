"""Results made once per key on the server, however many requests ask at the same moment: the
first request makes it, the others await the same task (a mesh's encoding, a demo sequence's
FEM solves: each holds a solve thread while it runs)."""

from __future__ import annotations

import asyncio
from collections import OrderedDict
from collections.abc import Awaitable, Callable, Hashable
from typing import Any


class Memo:
    """At most `size` results, the least recently asked dropped first; a failed making is not
    kept (the next request tries again, and every request that awaited it gets its error)."""

    def __init__(self, size: int) -> None:
        self.size = size
        self._kept: OrderedDict[Hashable, asyncio.Task] = OrderedDict()

    async def get(self, key: Hashable, make: Callable[[], Awaitable[Any]]) -> Any:
        task = self._kept.get(key)
        if task is None:
            task = asyncio.ensure_future(make())
            task.add_done_callback(lambda t: self._forget_failed(key, t))
            self._kept[key] = task
            while len(self._kept) > self.size:
                self._kept.popitem(last=False)  # an awaited task lives on with its awaiters
        self._kept.move_to_end(key)
        return await asyncio.shield(task)  # a request that goes away leaves the making running

    def _forget_failed(self, key: Hashable, task: asyncio.Task) -> None:
        if (task.cancelled() or task.exception() is not None) and self._kept.get(key) is task:
            del self._kept[key]

    def __len__(self) -> int:
        return len(self._kept)

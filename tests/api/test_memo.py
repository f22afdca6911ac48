"""Memo: a result made once per key however many requests ask together; failures not kept."""

import asyncio

import pytest

from service.api.memo import Memo


def test_concurrent_requests_share_one_making_and_a_failure_is_tried_again():
    made = []

    async def make(key, fail=False):
        made.append(key)
        await asyncio.sleep(0.05)
        if fail:
            raise RuntimeError("solver refused")
        return f"result {key}"

    async def scenario():
        memo = Memo(2)
        got = await asyncio.gather(*[memo.get("a", lambda: make("a")) for _ in range(5)])
        assert got == ["result a"] * 5 and made == ["a"]
        failed = await asyncio.gather(
            *[memo.get("b", lambda: make("b", fail=True)) for _ in range(3)], return_exceptions=True
        )
        assert all(isinstance(e, RuntimeError) for e in failed) and made == ["a", "b"]
        assert await memo.get("b", lambda: make("b")) == "result b" and made == ["a", "b", "b"]
        await memo.get("c", lambda: make("c"))  # over its size: the least recently asked ("a") goes
        assert len(memo) == 2
        assert await memo.get("a", lambda: make("a")) == "result a" and made.count("a") == 2

    asyncio.run(scenario())


def test_a_request_that_goes_away_leaves_the_making_to_the_others():
    async def scenario():
        memo, started, calls = Memo(4), asyncio.Event(), []

        async def make():
            calls.append(1)
            started.set()
            await asyncio.sleep(0.05)
            return 42

        first = asyncio.ensure_future(memo.get("k", make))
        await started.wait()
        first.cancel()
        with pytest.raises(asyncio.CancelledError):
            await first
        assert await memo.get("k", make) == 42 and len(calls) == 1  # not cancelled with its first asker

    asyncio.run(scenario())

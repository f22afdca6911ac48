"""The client's request bodies (clients/bodies.py, clients/encoding.py): what it refuses before
anything is sent, and what it sends so that the server's refusal names the fault, against the
real server, sync and async."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from clients import AsyncClient, Client


@pytest.mark.parametrize("encoding", ["msgpack", "json"])
def test_simulate_refuses_node_ids_that_are_not_integers(live, support, encoding):
    """simulate() cast its node ids to int64: support + 0.5 simulated the forces on `support`
    itself, and a bool mask became the ids 0 and 1. They are refused as a session's support
    is (API.md: node ids are integers); integer ids are simulated as before."""
    g = np.tile([0.0, 0.0, 5.0 / support.size], (support.size, 1))
    bad = [support + 0.5, np.ones(support.size, bool), list(support.astype(float))]

    with Client(live.url, encoding=encoding) as api:
        for nodes in bad:
            with pytest.raises(ValueError, match="forces' nodes must be integer node ids"):
                api.simulate("bar", nodes, g)
        assert api.simulate("bar", support, g)["displacement"].shape == (81, 3)

    async def main() -> None:
        async with AsyncClient(live.url, encoding=encoding) as api:
            for nodes in bad:
                with pytest.raises(ValueError, match="forces' nodes must be integer node ids"):
                    await api.simulate("bar", nodes, g)
            assert (await api.simulate("bar", support, g))["displacement"].shape == (81, 3)

    asyncio.run(main())

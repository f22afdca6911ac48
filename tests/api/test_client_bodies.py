"""The client's request bodies (clients/bodies.py, clients/encoding.py): what it refuses before
anything is sent, and what it sends so that the server's refusal names the fault, against the
real server, sync and async."""

from __future__ import annotations

import asyncio
import re

import numpy as np
import pytest

from clients import ApiError, AsyncClient, Client

from .conftest import start


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


@pytest.mark.parametrize("encoding", ["msgpack", "json"])
def test_non_finite_complex_and_too_large_input_is_refused_saying_why(live, support, clouds, encoding):
    """JSON sent NaN as null, so the server's 422 said "numbers only" where MessagePack's says
    "NaN or infinite"; complex points lost their imaginary part and were registered; a uint64
    id 2**64-1 wrapped to -1 ("must be non-negative"). NaN now reaches the server as NaN, whose
    422 names it in both encodings; complex values and too-large ids are refused before sending."""
    nan_points = np.where(np.arange(clouds[0].size).reshape(clouds[0].shape) == 5, np.nan, clouds[0])
    g = np.tile([0.0, 0.0, 1.0 / support.size], (support.size, 1))
    with Client(live.url, encoding=encoding) as api, api.open_session("bar", support=support) as s:
        with api.stream("bar", support=support) as st:
            for refused in (
                lambda: s.frame(nan_points),
                lambda: st.frame(nan_points),
                lambda: api.simulate("bar", support, np.where(g > 0, np.inf, g)),
                lambda: api.open_session("bar", alpha=float("nan")),
            ):
                with pytest.raises(ApiError) as err:
                    refused()
                assert err.value.status == 422 and re.search("NaN|finite", str(err.value.detail)), err.value
                assert "numbers only" not in str(err.value.detail), err.value
            for complex_ in (lambda: s.frame(clouds[0] + 1j), lambda: st.frame(clouds[0] + 0j)):
                with pytest.raises(ValueError, match="points must be real numbers, got dtype complex128"):
                    complex_()
            with pytest.raises(ValueError, match="points must be real numbers, got dtype bool"):
                s.frame(clouds[0] > 0)  # True is no coordinate
            with pytest.raises(ValueError, match="force values must be real numbers"):
                api.simulate("bar", support, g.astype(complex))
            huge = np.array([2**64 - 1], np.uint64)
            with pytest.raises(ValueError, match=f"support: node id {2**64 - 1} is too large"):
                st.frame(clouds[0], support=huge)
            with pytest.raises(ValueError, match="forces' nodes: node id .* is too large"):
                api.simulate("bar", huge, g[:1])
            assert st.frame(clouds[1], frame_id="after")["frame_id"] == "after"  # in step


def test_outputs_given_as_one_name_is_that_output(live, support, clouds):
    """outputs="forces" was split into its letters (a 422 "at most 4 items ..., not 6"): one
    name is a list of that one output, in a session and a stream alike."""
    with Client(live.url) as api:
        with api.open_session("bar", support=support, outputs="forces") as s:
            assert list(s.config["outputs"]) == ["forces"]
            assert set(s.frame(clouds[0])) >= {"forces"} and "displacement" not in s.frame(clouds[0])
        with api.stream("bar", support=support, outputs="forces") as st:
            assert list(st.config["outputs"]) == ["forces"]

    async def main() -> None:
        async with AsyncClient(live.url) as api, api.stream("bar", support=support, outputs="forces") as st:
            assert list(st.config["outputs"]) == ["forces"]

    asyncio.run(main())


def test_bool_node_ids_among_ints_and_complex_numbers_are_refused_before_sending(live, support, clouds):
    """[True, 2] went as the node ids [1, 2] (numpy reads a bool among ints as an int), where
    [True] alone was refused; a complex E or alpha reached the encoder, a TypeError "not JSON
    serializable". Both are refused with a ValueError before anything is sent, sync and async."""
    ids = [True, *support.tolist()[1:]]
    g = np.tile([0.0, 0.0, 1.0 / support.size], (support.size, 1))
    bools = "support must be integer node ids, got a bool among them"

    with Client(live.url) as api, api.stream("bar", support=support) as st:
        with pytest.raises(ValueError, match=bools):
            st.frame(clouds[0], support=ids)
        with pytest.raises(ValueError, match=bools):
            api.open_session("bar", support=ids)
        with pytest.raises(ValueError, match="forces' nodes must be integer node ids, got a bool"):
            api.simulate("bar", ids, g)
        with pytest.raises(ValueError, match=r"E must be a real number, got \(5000\+0j\)"):
            api.simulate("bar", support, g, E=5e3 + 0j)
        with pytest.raises(ValueError, match=r"alpha must be a real number, got 0\.001j"):
            api.open_session("bar", alpha=1e-3j)
        with pytest.raises(ValueError, match="alpha must be a real number"):
            api.stream("bar", alpha=np.complex128(1e-3))
        assert st.frame(clouds[1], frame_id="after")["frame_id"] == "after"  # in step

    async def main() -> None:
        async with AsyncClient(live.url) as api:
            with pytest.raises(ValueError, match=bools):
                await api.stream("bar", support=ids)
            with pytest.raises(ValueError, match="E must be a real number"):
                await api.simulate("bar", support, g, E=5e3 + 0j)
            with pytest.raises(ValueError, match="alpha must be a real number"):
                await api.open_session("bar", alpha=1e-3j)

    asyncio.run(main())


def test_a_stream_config_refused_before_sending_opens_no_socket(bar_store, support, clouds):
    """api.stream() with a config the client refuses (a bool among its support's ids) opened
    the socket first and left it open, counted against the server's max_sockets: on a server
    of one socket, the next stream was refused (503). The config is refused before connecting."""
    server = start(bar_store[0], instance_id="one_socket", max_sockets=1)
    ids = [True, *support.tolist()[1:]]
    try:
        with Client(server.url) as api:
            with pytest.raises(ValueError, match="support must be integer node ids"):
                api.stream("bar", support=ids)
            with api.stream("bar", support=support) as st:
                assert st.frame(clouds[0], frame_id="sync")["frame_id"] == "sync"

        async def main() -> None:
            async with AsyncClient(server.url) as api:
                with pytest.raises(ValueError, match="support must be integer node ids"):
                    await api.stream("bar", support=ids)
                async with api.stream("bar", support=support) as st:
                    assert (await st.frame(clouds[0], frame_id="async"))["frame_id"] == "async"

        asyncio.run(main())
    finally:
        server.stop()

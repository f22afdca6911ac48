"""How the client reads HTTP replies (clients/client.py): a server that is not the API, or a
proxy that redirects, is an ApiError that says so, never a result; sync and async."""

from __future__ import annotations

import asyncio
import contextlib
import http.server
import threading
from collections.abc import Iterator

import numpy as np
import pytest

from clients import ApiError, AsyncClient, Client, StreamError


@contextlib.contextmanager
def serving(handler: type[http.server.BaseHTTPRequestHandler]) -> Iterator[str]:
    """A plain HTTP server (not the API) on a free loopback port, in a thread: its base URL."""
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(10)


class _Answer(http.server.BaseHTTPRequestHandler):
    """Answers every request with ``status``, ``headers`` and ``body``."""

    protocol_version = "HTTP/1.1"  # websockets reads no HTTP/1.0 handshake reply
    status = 200
    headers_out: dict[str, str] = {}
    body = b""

    def _answer(self) -> None:
        self.rfile.read(int(self.headers.get("Content-Length") or 0))  # kept alive: the next request follows
        self.send_response(self.status)
        for k, v in {**self.headers_out, "Content-Length": str(len(self.body))}.items():
            self.send_header(k, v)
        self.end_headers()
        self.wfile.write(self.body)

    do_GET = do_POST = do_DELETE = _answer

    def log_message(self, *args) -> None:
        pass


class _Redirect(_Answer):
    """A proxy's `return 308 https://...`, as nginx sends it to plain HTTP."""

    status = 308
    headers_out = {"Location": "https://api.example.org/"}


class _Page(_Answer):
    """A web server that is not the API: 200 and an HTML page for every path."""

    headers_out = {"Content-Type": "text/html; charset=utf-8"}
    body = b"<!doctype html><html><body>It works!</body></html>"


def _calls(api):
    """Each kind of call, as (name, a function that makes it)."""
    return [
        ("health", api.health),
        ("models", api.models),
        ("mesh", lambda: api.mesh("bar")),
        ("simulate", lambda: api.simulate("bar", [1], [[0.0, 0.0, 1.0]])),
        ("open_session", lambda: api.open_session("bar")),
    ]


def _check(handler, status: int, words: str) -> None:
    with serving(handler) as url:
        for encoding in ("msgpack", "json"):
            with Client(url, encoding=encoding) as api:
                for name, call in _calls(api):
                    with pytest.raises(ApiError) as err:
                        call()
                    assert err.value.status == status and words in str(err.value.detail), (name, err.value)

            async def main(encoding: str) -> None:
                async with AsyncClient(url, encoding=encoding) as api:
                    for name, call in _calls(api):
                        with pytest.raises(ApiError) as err:
                            await call()
                        assert err.value.status == status and words in str(err.value.detail), (name, err.value)

            asyncio.run(main(encoding))


def test_a_redirect_is_an_api_error_that_names_where_it_points():
    """A proxy redirecting http to https (308): every call returned None (open_session then
    failed with a TypeError). The API never redirects: the client says where it was sent."""
    _check(_Redirect, 308, "redirected to https://api.example.org/: give the client that URL")
    with serving(_Redirect) as url:  # a stream's handshake, redirected the same way
        with Client(url) as api, pytest.raises(StreamError) as err:
            api.stream("bar")
        assert err.value.status == 308 and "redirected to https://api.example.org/" in err.value.detail

        async def main() -> None:
            async with AsyncClient(url) as api:
                with pytest.raises(StreamError) as err:
                    await api.stream("bar")
                assert err.value.status == 308 and "redirected to https://api.example.org/" in err.value.detail

        asyncio.run(main())


def test_a_page_from_a_server_that_is_not_the_api_is_an_api_error():
    """A web server answering 200 with HTML: health() returned {"detail": "<!doctype html>..."}
    as if it were the API's. The reply's media type says it is not."""
    _check(_Page, 200, "not an elastreg reply (text/html; charset=utf-8)")


def test_the_api_s_own_replies_still_read(live):
    """The check of the media type passes the API's JSON and MessagePack replies alike."""
    for encoding in ("msgpack", "json"):
        with Client(live.url, encoding=encoding) as api:
            assert api.health()["status"] == "ok" and api.models()[0]["id"] == "bar"


def test_model_ids_are_one_path_segment_never_another_path(live, support):
    """Model ids went into URL paths as they were: model("../health") returned /health,
    mesh("bar/..") and simulate("nope/../bar") reached bar, model("bar?x") read "?x" as a query
    and returned bar's summary. An id with "/", ".", ".." is refused before anything is sent
    (no model's id holds one), and the rest is quoted: "bar?x" is an unknown model, a 404."""
    g = np.tile([0.0, 0.0, 1.0 / support.size], (support.size, 1))
    paths = ["../health", "bar/mesh", "nope/../bar", "..", ".", ""]

    def calls(api):
        for model in paths:
            yield model, lambda m=model: api.model(m)
            yield model, lambda m=model: api.mesh(m)
            yield model, lambda m=model: api.simulate(m, support, g)

    with Client(live.url) as api:
        for model, call in calls(api):
            with pytest.raises(ValueError, match="names no model: an id is one URL path segment") as err:
                call()
            assert str(err.value).startswith(f"model id {model!r}"), err.value
        for model in ("bar?x", "bar#x", "bar%2Fmesh"):
            with pytest.raises(ApiError) as err:
                api.model(model)
            assert err.value.status == 404, (model, err.value)
        assert api.model("bar")["n_nodes"] == 81

    async def main() -> None:
        async with AsyncClient(live.url) as api:
            for model, call in calls(api):
                with pytest.raises(ValueError, match="names no model") as err:
                    await call()
                assert str(err.value).startswith(f"model id {model!r}"), err.value
            with pytest.raises(ApiError) as err:
                await api.model("bar?x")
            assert err.value.status == 404
            assert (await api.mesh("bar"))["nodes"].shape == (81, 3)

    asyncio.run(main())


class _ErrorPage(_Answer):
    """A proxy's 502 page in front of a stopped API: 40 KB of HTML."""

    status = 502
    headers_out = {"Content-Type": "text/html"}
    body = b"<html>\n<head><title>502 Bad Gateway</title></head>\n<body>" + b"<p>padding</p>" * 3000 + b"</body></html>"


def test_another_servers_error_page_is_named_and_cut_short():
    """A proxy's 502 page became the ApiError's detail whole (40 KB of HTML in every log line
    that printed the error). Now the detail says it is no API reply, from where, and keeps the
    page's first 200 characters, its whitespace folded."""
    _check(_ErrorPage, 502, "not an elastreg reply (text/html) from http://127.0.0.1:")
    with serving(_ErrorPage) as url, Client(url) as api, pytest.raises(ApiError) as err:
        api.health()
    assert "<html> <head><title>502 Bad Gateway</title></head>" in err.value.detail
    assert len(err.value.detail) < 300 and err.value.detail.endswith(" ...")

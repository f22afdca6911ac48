"""A Python client for the elastreg API: HTTP and WebSocket, sync and async, JSON and
MessagePack; NumPy arrays in, NumPy arrays out.

>>> with Client("http://127.0.0.1:8000") as api:                      # doctest: +SKIP
...     mesh = api.mesh("phantom")                                     # arrays: nodes (n, 3), ...
...     with api.stream("phantom", support=ids) as stream:             # a WebSocket session
...         result = stream.frame(points)                              # (m, 3) in, a dict out
...     result["displacement"].shape                                    # (n, 3)

>>> with Client(url) as api, api.watch(session_id) as frames:           # doctest: +SKIP
...     for frame in frames:                                           # a second screen's loop
...         show(frame["points"], frame["result"])                     # slow? the newest comes next

HTTP sessions (``open_session``) live in the server process that opened them: behind several
processes, route them with affinity (docs/usage.md, "Scaling out") or use ``stream``, whose session lives
with its connection. With ``encoding="msgpack"`` (the default) arrays travel as packed bytes.
On a server with tokens pass ``token=`` (sent as ``Authorization: Bearer``, on the WebSocket's
handshake too); over HTTPS, ``verify=`` takes a CA file for a private certificate.

This module holds the clients (:class:`Client`, :class:`AsyncClient`) and their HTTP sessions;
the WebSocket handles are in :mod:`.sockets`, the errors in :mod:`.errors`, the wire format in
:mod:`.encoding` and the requests' bodies in :mod:`.bodies`; their public names import from here too.
"""

from __future__ import annotations

import importlib.util
import os
import re
from urllib.parse import quote

try:  # the [client] extra: httpx here, websockets at a stream's first use
    import httpx
except ImportError as err:  # pragma: no cover
    raise ImportError("the elastreg client needs httpx: pip install 'elastreg[client]'") from err
if importlib.util.find_spec("websockets") is None:  # pragma: no cover
    raise ImportError("the elastreg client needs websockets: pip install 'elastreg[client]'")

from .bodies import config_body, frame_body, simulate_body
from .encoding import JSON_MEDIA, MSGPACK_MEDIA, decode, encode
from .errors import ApiError, foreign_page, redirected, retry_after
from .errors import StreamError as StreamError  # importable from here, as it always was
from .sockets import AsyncStream, AsyncWatch, Opening, Stream, Watch, handshake_refused, refused_status

#: the media types of the API's bodies: anything else answering 2xx is not the API
_API_MEDIA = re.compile(r"^application/(json|msgpack)\b")


def _ws_url(base_url: str, path: str = "/stream", query: str | None = None) -> str:
    url = httpx.URL(base_url)
    scheme = "wss" if url.scheme == "https" else "ws"
    return str(url.copy_with(scheme=scheme, path=url.path.rstrip("/") + path, query=query and query.encode()))


def _model_path(model: str, tail: str = "") -> str:
    """``/models/{model}{tail}``, the id quoted as one path segment: "bar?x" is no query. The
    server decodes %2F before routing, so an id with "/" (or ".", "..") would reach another
    path ("../health" the health check): no model's id holds one, and it is refused here."""
    if not isinstance(model, str) or model in ("", ".", "..") or "/" in model:
        raise ValueError(f"model id {model!r:.80} names no model: an id is one URL path segment, no '/', '.' or '..'")
    return f"/models/{quote(model, safe='')}{tail}"


def viewer_url(base_url: str, session_id: str) -> str:
    """The page that watches a session live (API.md, "Watching a session, and the viewer")."""
    return f"{base_url.rstrip('/')}/viewer?session={quote(session_id, safe='')}"


def _watch_url(base_url: str, session_id: str, encoding: str) -> str:
    path = f"/sessions/{quote(session_id, safe='')}/watch"
    return _ws_url(base_url, path, "encoding=msgpack" if encoding == "msgpack" else None)


def _ssl_context(verify):
    """An SSL context for ``verify``: True (the system's CAs), a CA file's path, or a context."""
    import ssl

    if isinstance(verify, ssl.SSLContext):
        return verify
    if isinstance(verify, (str, os.PathLike)):
        return ssl.create_default_context(cafile=os.fspath(verify))
    if verify is True:
        return ssl.create_default_context()
    raise ValueError("verify must be True, a CA file's path or an ssl.SSLContext (build your own for no checks)")


class _Base:
    """What the sync and async clients share: settings, headers, TLS, and a reply's reading."""

    def __init__(self, base_url: str, encoding: str, timeout: float, token: str | None, verify) -> None:
        if encoding not in ("msgpack", "json"):
            raise ValueError("encoding must be 'msgpack' or 'json'")
        self.base_url = base_url.rstrip("/")
        self.encoding = encoding
        self.timeout = timeout
        media = MSGPACK_MEDIA if encoding == "msgpack" else JSON_MEDIA
        self.headers = {"content-type": media, "accept": media}
        self.ws_headers = {}
        if token is not None:  # the same header on HTTP and in the WebSocket's handshake
            self.headers["authorization"] = self.ws_headers["authorization"] = f"Bearer {token}"
        self.tls = _ssl_context(verify) if self.base_url.startswith("https:") else None

    def _http_options(self) -> dict:
        return {
            "base_url": self.base_url,
            "timeout": self.timeout,
            "headers": self.headers,
            "verify": self.tls if self.tls is not None else True,
        }

    def _ws_options(self, max_size) -> dict:
        options = {"max_size": max_size, "compression": None, "additional_headers": self.ws_headers}
        if self.tls is not None:
            options["ssl"] = self.tls
        return options

    def _result(self, r: httpx.Response):
        media = r.headers.get("content-type", "")
        if r.status_code == 204:
            return None
        if r.is_redirect:  # a proxy's http -> https, say: the API itself never redirects
            location = r.headers.get("location")
            raise ApiError(r.status_code, redirected(str(r.url.join(location)) if location else None))
        try:
            body = decode(r.content, "msgpack" if "msgpack" in media else "json") if r.content else None
        except Exception:
            body = None
        if r.status_code >= 400:
            detail = body.get("detail") if isinstance(body, dict) else body
            if body is None and r.content:  # another server's error page: said to be one, and its start
                detail = foreign_page(media, r.url, r.text)
            instance, retry = r.headers.get("x-elastreg-instance"), retry_after(r.headers.get("retry-after"))
            raise ApiError(r.status_code, detail, instance, retry)
        if body is None or not _API_MEDIA.match(media):
            # another server's page (a wrong port, a proxy's login page), never the API's result
            raise ApiError(r.status_code, f"not an elastreg reply ({media or 'no content-type'}) from {r.url}")
        return body


# -- sync ----------------------------------------------------------------------------------------


class Client(_Base):
    """The API over HTTP (httpx, one keep-alive connection pool) and WebSocket streams."""

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8000",
        *,
        encoding: str = "msgpack",
        timeout: float = 60.0,
        token: str | None = None,
        verify=True,
    ) -> None:
        super().__init__(base_url, encoding, timeout, token, verify)
        self.http = httpx.Client(**self._http_options())

    def _call(self, method: str, path: str, body=None):
        content = None if body is None else encode(body, self.encoding)
        return self._result(self.http.request(method, path, content=content))

    def health(self) -> dict:
        return self._call("GET", "/health")

    def models(self) -> list[dict]:
        return self._call("GET", "/models")

    def model(self, model: str) -> dict:
        return self._call("GET", _model_path(model))

    def mesh(self, model: str) -> dict:
        """nodes (n, 3), tets (t, 4), surface_faces (f, 3), surface_nodes, fixed_nodes, region_nodes."""
        return self._call("GET", _model_path(model, "/mesh"))

    def simulate(self, model: str, nodes, values, *, method: str = "network", E: float | None = None) -> dict:
        """Displacement (n, 3) under forces ``values`` (k, 3) on ``nodes`` (k,)."""
        return self._call("POST", _model_path(model, "/simulate"), simulate_body(nodes, values, method, E))

    def open_session(self, model: str, **config) -> SessionHandle:
        """An HTTP session (``POST /sessions``); config as in API.md (support, alpha, outputs...)."""
        r = self._call("POST", "/sessions", config_body(model, config))
        return SessionHandle(self, r["session"], r["config"])

    def _connect(self, url: str, max_size: int | None):
        """A WebSocket to `url`; a handshake the server refuses (the socket limit's 503, with its
        Retry-After) raises :class:`StreamError`."""
        from websockets.exceptions import WebSocketException
        from websockets.sync.client import connect

        try:
            return connect(url, open_timeout=self.timeout, **self._ws_options(max_size))
        except WebSocketException as exc:
            status = refused_status(exc)
            if status is None:
                raise
            raise handshake_refused(status) from None

    def stream(self, model: str, *, max_size: int | None = 1 << 27, **config) -> Stream:
        """A WebSocket stream (``/stream``) whose session lives with the connection. A refusal
        (at the session or socket limit: a 503 with ``retry_after``) raises :class:`StreamError`."""
        body = config_body(model, config)  # bad input refused before a socket is opened, not left open
        ws = self._connect(_ws_url(self.base_url), max_size)
        ws.__enter__()  # the Stream owns the connection (and closes it): websockets >= 17 asks for this
        return Stream(ws, self.encoding, body, self.timeout)

    def watch(self, session_id: str, *, max_size: int | None = 1 << 27) -> Watch:
        """Watch a session (``WS /sessions/{id}/watch``): its frames as they are solved."""
        ws = self._connect(_watch_url(self.base_url, session_id, self.encoding), max_size)
        ws.__enter__()  # the Watch owns the connection, as a Stream does
        return Watch(ws, self.encoding, self.timeout)

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class SessionHandle:
    """An open HTTP session: ``frame(points)`` registers one frame; ``close()`` ends it."""

    def __init__(self, client: Client, session_id: str, config: dict) -> None:
        self.client = client
        self.id = session_id
        self.config = config

    def frame(self, points, *, support=None, frame_id=None) -> dict:
        return self.client._call("POST", f"/sessions/{self.id}/frames", frame_body(points, support, frame_id))

    def info(self) -> dict:
        return self.client._call("GET", f"/sessions/{self.id}")

    def close(self) -> None:
        self.client._call("DELETE", f"/sessions/{self.id}")

    def __enter__(self) -> SessionHandle:
        return self

    def __exit__(self, *exc) -> None:
        try:
            self.close()
        except ApiError:
            pass


# -- async ---------------------------------------------------------------------------------------


class AsyncClient(_Base):
    """The same API for asyncio (httpx.AsyncClient and websockets' asyncio client)."""

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8000",
        *,
        encoding: str = "msgpack",
        timeout: float = 60.0,
        max_connections: int = 100,
        token: str | None = None,
        verify=True,
    ) -> None:
        super().__init__(base_url, encoding, timeout, token, verify)
        self.http = httpx.AsyncClient(limits=httpx.Limits(max_connections=max_connections), **self._http_options())

    async def _call(self, method: str, path: str, body=None):
        content = None if body is None else encode(body, self.encoding)
        return self._result(await self.http.request(method, path, content=content))

    async def health(self) -> dict:
        return await self._call("GET", "/health")

    async def models(self) -> list[dict]:
        return await self._call("GET", "/models")

    async def model(self, model: str) -> dict:
        return await self._call("GET", _model_path(model))

    async def mesh(self, model: str) -> dict:
        return await self._call("GET", _model_path(model, "/mesh"))

    async def simulate(self, model: str, nodes, values, *, method: str = "network", E: float | None = None) -> dict:
        return await self._call("POST", _model_path(model, "/simulate"), simulate_body(nodes, values, method, E))

    async def open_session(self, model: str, **config) -> AsyncSessionHandle:
        r = await self._call("POST", "/sessions", config_body(model, config))
        return AsyncSessionHandle(self, r["session"], r["config"])

    async def _connect(self, url: str, max_size: int | None):
        """See :meth:`Client._connect`."""
        from websockets import connect
        from websockets.exceptions import WebSocketException

        try:
            return await connect(url, open_timeout=self.timeout, **self._ws_options(max_size))
        except WebSocketException as exc:
            status = refused_status(exc)
            if status is None:
                raise
            raise handshake_refused(status) from None

    def stream(self, model: str, *, max_size: int | None = 1 << 27, **config) -> Opening[AsyncStream]:
        """A stream; see :meth:`Client.stream`. ``async with api.stream(...) as stream`` closes it
        at the block's end; ``stream = await api.stream(...)`` leaves that to the caller."""
        return Opening(self._stream(model, max_size, config))

    async def _stream(self, model: str, max_size: int | None, config: dict) -> AsyncStream:
        body = config_body(model, config)  # as Client.stream's: refused before a socket is opened
        ws = await self._connect(_ws_url(self.base_url), max_size)
        stream = AsyncStream(ws, self.encoding, self.timeout)
        await stream._open(body)
        return stream

    def watch(self, session_id: str, *, max_size: int | None = 1 << 27) -> Opening[AsyncWatch]:
        """Watch a session; see :meth:`Client.watch`. Awaited or in ``async with``, as :meth:`stream`."""
        return Opening(self._watch(session_id, max_size))

    async def _watch(self, session_id: str, max_size: int | None) -> AsyncWatch:
        ws = await self._connect(_watch_url(self.base_url, session_id, self.encoding), max_size)
        watch = AsyncWatch(ws, self.encoding, self.timeout)
        await watch._open()
        return watch

    async def aclose(self) -> None:
        await self.http.aclose()

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc) -> None:
        await self.aclose()


class AsyncSessionHandle:
    """An open HTTP session (asyncio); see :class:`SessionHandle`."""

    def __init__(self, client: AsyncClient, session_id: str, config: dict) -> None:
        self.client = client
        self.id = session_id
        self.config = config

    async def frame(self, points, *, support=None, frame_id=None) -> dict:
        return await self.client._call("POST", f"/sessions/{self.id}/frames", frame_body(points, support, frame_id))

    async def info(self) -> dict:
        return await self.client._call("GET", f"/sessions/{self.id}")

    async def close(self) -> None:
        await self.client._call("DELETE", f"/sessions/{self.id}")

    async def __aenter__(self) -> AsyncSessionHandle:
        return self

    async def __aexit__(self, *exc) -> None:
        try:
            await self.close()
        except ApiError:
            pass

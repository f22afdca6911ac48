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
processes, route them with affinity (see the README) or use ``stream``, whose session lives
with its connection. With ``encoding="msgpack"`` (the default) arrays travel as packed bytes.
On a server with tokens pass ``token=`` (sent as ``Authorization: Bearer``, on the WebSocket's
handshake too); over HTTPS, ``verify=`` takes a CA file for a private certificate.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
from typing import Any, Self
from urllib.parse import quote

import msgpack
import numpy as np

try:  # the [client] extra: httpx here, websockets at a stream's first use
    import httpx
except ImportError as err:  # pragma: no cover
    raise ImportError("the elastreg client needs httpx: pip install 'elastreg[client]'") from err
if importlib.util.find_spec("websockets") is None:  # pragma: no cover
    raise ImportError("the elastreg client needs websockets: pip install 'elastreg[client]'")

try:  # optional: faster JSON that writes NumPy arrays itself
    import orjson
except ImportError:  # pragma: no cover
    orjson = None

JSON_MEDIA = "application/json"
MSGPACK_MEDIA = "application/msgpack"
_FLOAT_KEYS = frozenset(
    {"displacement", "surface_displacement", "forces", "stress", "net_force", "nodes", "values", "points"}
)
_INT_KEYS = frozenset({"support", "tets", "surface_faces", "surface_nodes", "fixed_nodes", "region_nodes", "matching"})
_PACKED = frozenset({"dtype", "shape", "data"})
_DTYPES = {"<f4", "<f8", "<i4", "<i8"}


class ApiError(RuntimeError):
    """The server refused a request: ``status`` (HTTP code, or the stream error's code),
    ``detail`` (its explanation) and, on a 503 (saturated, at the session limit, shutting down),
    ``retry_after`` (seconds to wait before trying again: an HTTP reply's Retry-After, a stream
    error's ``retry_after``; None where the server gave none)."""

    def __init__(self, status: int, detail: Any, instance: str | None = None, retry_after: float | None = None) -> None:
        super().__init__(f"{status}: {detail}")
        self.status = status
        self.detail = detail
        self.instance = instance
        self.retry_after = retry_after


def _retry_after(value: str | None) -> float | None:
    """Retry-After in seconds: the server sends delta-seconds; an HTTP date (another proxy's) or
    a bad value gives None rather than a second error."""
    try:
        return float(value) if value is not None else None
    except ValueError:
        return None


class StreamError(ApiError):
    """A stream's or a watch's error: an error message (``close_code`` None: the stream stays
    open), or a socket the server closed (``close_code`` set, and ``reason`` its words: a
    refused first message, 1008; an idle stream past ``session_ttl_s`` or a watched session
    that ended, 1000; a message over the size limit, 1009; a connection lost without a close
    frame, 1006). A closed socket's ``status`` is 0 and its ``__cause__`` websockets' own
    ``ConnectionClosed``; a new stream is needed."""

    def __init__(
        self,
        status: int,
        detail: Any,
        frame_id=None,
        close_code: int | None = None,
        retry_after: float | None = None,
        reason: str = "",
    ) -> None:
        super().__init__(status, detail, retry_after=retry_after)
        if status == 0 and close_code is not None:  # a close, not an error message: no status to show
            self.args = (f"closed {close_code}: {detail}",)
        self.frame_id = frame_id
        self.close_code = close_code
        self.reason = reason


def _stream_error(e, close_code: int | None = None) -> StreamError:
    """The StreamError of a stream's ``{"error": {...}}`` message."""
    if not isinstance(e, dict):
        return StreamError(0, e, close_code=close_code)
    retry = e.get("retry_after")
    retry = float(retry) if isinstance(retry, (int, float)) and not isinstance(retry, bool) else None
    return StreamError(int(e.get("code", 0)), e.get("detail"), e.get("frame_id"), close_code, retry)


# -- encoding ------------------------------------------------------------------------------------


def _pack(a: np.ndarray) -> dict:
    if a.dtype.kind == "f":
        dt = "<f4" if a.dtype.itemsize == 4 else "<f8"
    elif a.dtype.kind in "iu":
        dt = "<i4" if a.dtype.kind == "i" and a.dtype.itemsize <= 4 else "<i8"
    else:
        raise TypeError(f"cannot send an array of dtype {a.dtype}")
    a = np.ascontiguousarray(a, dtype=dt)
    return {"dtype": dt, "shape": list(a.shape), "data": a.tobytes()}


def _outgoing(obj, encoding: str):
    if isinstance(obj, np.ndarray):
        if encoding == "msgpack":
            return _pack(obj)
        return obj if orjson is not None else obj.tolist()
    if isinstance(obj, dict):
        return {k: _outgoing(v, encoding) for k, v in obj.items() if v is not None}
    if isinstance(obj, (list, tuple)):
        return [_outgoing(v, encoding) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def encode(obj, encoding: str) -> bytes:
    """A request body (arrays packed for MessagePack, listed for JSON; None values left out)."""
    obj = _outgoing(obj, encoding)
    if encoding == "msgpack":
        return msgpack.packb(obj, use_bin_type=True)
    if orjson is not None:
        return orjson.dumps(obj, default=_tolist, option=orjson.OPT_SERIALIZE_NUMPY)
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def _tolist(obj):
    if isinstance(obj, (np.ndarray, np.generic)):
        return obj.tolist()
    raise TypeError(f"cannot encode {type(obj).__name__} as JSON")


def _incoming(obj, key: str | None = None):
    if isinstance(obj, dict):
        if obj.keys() == _PACKED and obj.get("dtype") in _DTYPES:
            return np.frombuffer(obj["data"], dtype=obj["dtype"]).reshape(obj["shape"]).copy()
        return {k: _incoming(v, k) for k, v in obj.items()}
    if isinstance(obj, list):
        if key in _FLOAT_KEYS:
            return np.asarray(obj, dtype=np.float64)  # JSON null (a non-finite value) -> NaN
        if key in _INT_KEYS:
            return np.asarray(obj, dtype=np.int64)
        return [_incoming(v) for v in obj]
    return obj


def decode(data: bytes | str, encoding: str):
    """A reply body, arrays as NumPy arrays (packed ones copied: writable)."""
    if encoding == "msgpack":
        obj = msgpack.unpackb(data, raw=False)
    else:
        obj = orjson.loads(data) if orjson is not None else json.loads(data)
    return _incoming(obj)


def _node_ids(ids, what: str) -> np.ndarray:
    """Node ids as int64, refused here if they are not integers: a cast would truncate 1.5 to 1
    and register over another node than the one meant (the server refuses them too)."""
    a = np.asarray(ids)
    if a.dtype.kind not in "iu":
        raise ValueError(f"{what} must be integer node ids, got dtype {a.dtype}")
    return a.astype(np.int64, copy=False)


def _frame_body(points, support, frame_id) -> dict:
    return {
        "points": np.asarray(points, dtype=np.float64),
        "support": None if support is None else _node_ids(support, "support"),
        "frame_id": frame_id,
    }


def _config_body(model: str, config: dict) -> dict:
    body = {"model": model, **config}
    for key in ("support", "matching"):
        if body.get(key) is not None:
            body[key] = _node_ids(body[key], key)
    if body.get("outputs") is not None:
        body["outputs"] = list(body["outputs"])
    return body


def _ws_url(base_url: str, path: str = "/stream", query: str | None = None) -> str:
    url = httpx.URL(base_url)
    scheme = "wss" if url.scheme == "https" else "ws"
    return str(url.copy_with(scheme=scheme, path=url.path.rstrip("/") + path, query=query and query.encode()))


def viewer_url(base_url: str, session_id: str) -> str:
    """The page that watches a session live (API.md, "Watching a session, and the viewer")."""
    return f"{base_url.rstrip('/')}/viewer?session={quote(session_id, safe='')}"


def _watch_url(base_url: str, session_id: str, encoding: str) -> str:
    path = f"/sessions/{quote(session_id, safe='')}/watch"
    return _ws_url(base_url, path, "encoding=msgpack" if encoding == "msgpack" else None)


def _handshake_refused(exc) -> StreamError:
    """The StreamError of a handshake the server answered with an HTTP status instead of a
    socket (the socket limit's 503, with its Retry-After)."""
    r = exc.response
    try:
        detail = json.loads(r.body)["detail"]
    except Exception:
        detail = r.body.decode(errors="replace") if r.body else r.reason_phrase
    return StreamError(r.status_code, detail, retry_after=_retry_after(r.headers.get("Retry-After")))


def _reply(message, encoding: str) -> dict:
    obj = decode(message, "msgpack" if isinstance(message, (bytes, bytearray)) else "json")
    if isinstance(obj, dict) and set(obj) == {"error"}:
        raise _stream_error(obj["error"])
    return obj


_OUT_OF_STEP = "a reply timed out, so this stream's replies no longer match its frames: open a new stream"

# -- sync ----------------------------------------------------------------------------------------


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
    def __init__(self, base_url: str, encoding: str, token: str | None = None, verify=True) -> None:
        if encoding not in ("msgpack", "json"):
            raise ValueError("encoding must be 'msgpack' or 'json'")
        self.base_url = base_url.rstrip("/")
        self.encoding = encoding
        media = MSGPACK_MEDIA if encoding == "msgpack" else JSON_MEDIA
        self.headers = {"content-type": media, "accept": media}
        self.ws_headers = {}
        if token is not None:  # the same header on HTTP and in the WebSocket's handshake
            self.headers["authorization"] = self.ws_headers["authorization"] = f"Bearer {token}"
        self.tls = _ssl_context(verify) if self.base_url.startswith("https:") else None

    def _ws_options(self, max_size) -> dict:
        options = {"max_size": max_size, "compression": None, "additional_headers": self.ws_headers}
        if self.tls is not None:
            options["ssl"] = self.tls
        return options

    def _result(self, r: httpx.Response):
        kind = "msgpack" if "msgpack" in r.headers.get("content-type", "") else "json"
        if r.status_code == 204:
            return None
        try:
            body = decode(r.content, kind) if r.content else None
        except Exception:
            body = {"detail": r.text}
        if r.status_code >= 400:
            detail = body.get("detail") if isinstance(body, dict) else body
            instance, retry = r.headers.get("x-elastreg-instance"), _retry_after(r.headers.get("retry-after"))
            raise ApiError(r.status_code, detail, instance, retry)
        return body


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
        super().__init__(base_url, encoding, token, verify)
        self.timeout = timeout
        self.http = httpx.Client(
            base_url=self.base_url,
            timeout=timeout,
            headers=self.headers,
            verify=self.tls if self.tls is not None else True,
        )

    def _call(self, method: str, path: str, body=None):
        content = None if body is None else encode(body, self.encoding)
        return self._result(self.http.request(method, path, content=content))

    def health(self) -> dict:
        return self._call("GET", "/health")

    def models(self) -> list[dict]:
        return self._call("GET", "/models")

    def model(self, model: str) -> dict:
        return self._call("GET", f"/models/{model}")

    def mesh(self, model: str) -> dict:
        """nodes (n, 3), tets (t, 4), surface_faces (f, 3), surface_nodes, fixed_nodes, region_nodes."""
        return self._call("GET", f"/models/{model}/mesh")

    def simulate(self, model: str, nodes, values, *, method: str = "network", E: float | None = None) -> dict:
        """Displacement (n, 3) under forces ``values`` (k, 3) on ``nodes`` (k,)."""
        body = {
            "forces": {"nodes": np.asarray(nodes, np.int64), "values": np.asarray(values, np.float64)},
            "method": method,
            "E": E,
        }
        return self._call("POST", f"/models/{model}/simulate", body)

    def open_session(self, model: str, **config) -> SessionHandle:
        """An HTTP session (``POST /sessions``); config as in API.md (support, alpha, outputs...)."""
        r = self._call("POST", "/sessions", _config_body(model, config))
        return SessionHandle(self, r["session"], r["config"])

    def _connect(self, url: str, max_size: int | None):
        """A WebSocket to `url`; a handshake the server refuses (the socket limit's 503, with its
        Retry-After) raises :class:`StreamError`."""
        from websockets.exceptions import InvalidStatus
        from websockets.sync.client import connect

        try:
            return connect(url, open_timeout=self.timeout, **self._ws_options(max_size))
        except InvalidStatus as exc:
            raise _handshake_refused(exc) from None

    def stream(self, model: str, *, max_size: int | None = 1 << 27, **config) -> Stream:
        """A WebSocket stream (``/stream``) whose session lives with the connection. A refusal
        (at the session or socket limit: a 503 with ``retry_after``) raises :class:`StreamError`."""
        ws = self._connect(_ws_url(self.base_url), max_size)
        ws.__enter__()  # the Stream owns the connection (and closes it): websockets >= 17 asks for this
        return Stream(ws, self.encoding, _config_body(model, config), self.timeout)

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
        return self.client._call("POST", f"/sessions/{self.id}/frames", _frame_body(points, support, frame_id))

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


def _close_code(ws) -> int | None:
    """The close code of a socket the server is closing (after refusing its first message),
    waiting 2 s at most; None if it stays open."""
    from websockets.exceptions import ConnectionClosed

    try:
        ws.recv(timeout=2.0)
    except ConnectionClosed as exc:
        return _closed_code(exc)
    except Exception:
        pass
    return None


async def _aclose_code(ws) -> int | None:
    """:func:`_close_code` for an asyncio socket."""
    import asyncio

    from websockets.exceptions import ConnectionClosed

    try:
        await asyncio.wait_for(ws.recv(), 2.0)
    except ConnectionClosed as exc:
        return _closed_code(exc)
    except Exception:
        pass
    return None


def _is_error(message) -> bool:
    """Whether a stream's or a watch's message is its error, ``{"error": {...}}``."""
    obj = decode(message, "msgpack" if isinstance(message, (bytes, bytearray)) else "json")
    return isinstance(obj, dict) and set(obj) == {"error"}


def _closed_code(exc: Exception) -> int | None:
    rcvd = getattr(exc, "rcvd", None)
    return getattr(rcvd, "code", None)


# RFC 6455 7.1.5: the close code of a connection that ended without a close frame received
_ABNORMAL_CLOSURE = 1006


def _closed_by_server(exc: Exception, what: str = "stream") -> StreamError:
    """The StreamError of a socket found closed (``exc``, websockets' ConnectionClosed): the
    server's close code and reason (1006 where no close frame came), status 0."""
    rcvd = getattr(exc, "rcvd", None)
    code = _closed_code(exc) or _ABNORMAL_CLOSURE
    reason = getattr(rcvd, "reason", "") or ""
    if rcvd is None:  # no close frame: the connection dropped (the server gone, a network cut)
        detail = f"the {what}'s connection was lost without a close frame ({exc})"
    else:
        detail = reason or f"the server closed the {what} ({rcvd})"
    return StreamError(0, detail, close_code=code, reason=reason)


@contextlib.contextmanager
def _closes_as_stream_error(what: str = "stream"):
    """Raise a socket found closed as :class:`StreamError` (websockets' exception its cause)."""
    from websockets.exceptions import ConnectionClosed

    try:
        yield
    except ConnectionClosed as exc:
        raise _closed_by_server(exc, what) from exc


def _opened(first, wait_close) -> tuple[str, dict]:
    """The session id and config from a stream's first reply, or StreamError (the server closes
    a stream whose first message it refused; ``wait_close()`` returns its close code)."""
    obj = decode(first, "msgpack" if isinstance(first, (bytes, bytearray)) else "json")
    if isinstance(obj, dict) and set(obj) == {"error"}:
        raise _stream_error(obj["error"], close_code=wait_close())
    return obj["session"], obj["config"]


class _Socket:
    """A handle that owns its WebSocket (``ws``): closed with it, or by leaving its block."""

    ws: Any

    def close(self) -> None:
        self.ws.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _AsyncSocket:
    """:class:`_Socket` for an asyncio WebSocket."""

    ws: Any

    async def close(self) -> None:
        await self.ws.close()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()


class Stream(_Socket):
    """A WebSocket stream (sync): ``send`` frames (they may be pipelined), ``recv`` results in
    order, or ``frame`` for both. A stream error raises :class:`StreamError` (a 503's with
    ``retry_after``, the seconds to wait); the stream goes on. A stream the server closed (idle
    past its ``session_ttl_s``, shutting down, a message over its size limit) raises
    :class:`StreamError` too, with ``close_code`` and ``reason`` set: open a new stream."""

    def __init__(self, ws, encoding: str, config: dict, timeout: float | None = None) -> None:
        self.ws = ws
        self.encoding = encoding
        self.timeout = timeout
        from websockets.exceptions import ConnectionClosed

        self._out_of_step = False
        try:
            self._send_raw(config)
            first = ws.recv(timeout=timeout)
            self.session, self.config = _opened(first, lambda: _close_code(ws))
        except ConnectionClosed as exc:
            try:  # the server may have refused the handshake's token before the config was sent
                _reply(ws.recv(timeout=0.5), encoding)
            except StreamError as refused:
                refused.close_code = _closed_code(exc)
                raise refused from None
            except Exception:
                pass
            raise _closed_by_server(exc) from exc
        except BaseException:
            ws.close()
            raise

    def _send_raw(self, body: dict) -> None:
        data = encode(body, self.encoding)
        self.ws.send(data if self.encoding == "msgpack" else data.decode())

    def send(self, points, *, support=None, frame_id=None) -> None:
        with _closes_as_stream_error():
            self._send_raw(_frame_body(points, support, frame_id))

    def recv(self, timeout: float | None = None) -> dict:
        with _closes_as_stream_error():
            message = self.ws.recv(timeout=timeout if timeout is not None else self.timeout)
        return _reply(message, self.encoding)

    def frame(self, points, *, support=None, frame_id=None) -> dict:
        """Send one frame and return its result. After a reply that timed out, the stream is out
        of step (that reply may still come, and would be taken for the next frame's): a
        StreamError says so, and a new stream is needed."""
        if self._out_of_step:
            raise StreamError(0, _OUT_OF_STEP)
        self.send(points, support=support, frame_id=frame_id)
        try:
            return self.recv()
        except TimeoutError:
            self._out_of_step = True
            raise


def _ack(seq: int, encoding: str) -> bytes | str:
    data = encode({"ack": seq}, encoding)
    return data if encoding == "msgpack" else data.decode()


def _watching(hello, close_code) -> tuple[str, str, dict]:
    """The session, model and config from a watch's first message, or StreamError (the server
    refuses an unknown session, or another token's, and closes the socket)."""
    obj = decode(hello, "msgpack" if isinstance(hello, (bytes, bytearray)) else "json")
    if isinstance(obj, dict) and set(obj) == {"error"}:
        raise _stream_error(obj["error"], close_code=close_code())
    return obj["watching"], obj["model"], obj["config"]


class Watch(_Socket):
    """A session's frames as it solves them (sync): ``{"seq", "time", "points", "result"}``.

    Iterate (or call ``recv``) for the next frame, waiting while the session is idle; iteration
    ends when the session does. ``timeout`` bounds the wait for the first message only. Each
    frame is acknowledged when the next is asked for (the caller has handled it), so the server
    sends only a frame or two ahead: a caller slower than the session gets the newest frame next
    and the ones it missed are the gaps in ``seq``. A closed watch raises :class:`StreamError`
    with its ``close_code`` (1000 when the session ended)."""

    def __init__(self, ws, encoding: str, timeout: float | None = None) -> None:
        self.ws = ws
        self.encoding = encoding
        self._handled: int | None = None  # the seq returned last, acknowledged at the next recv
        from websockets.exceptions import ConnectionClosed

        try:
            self.session, self.model, self.config = _watching(ws.recv(timeout=timeout), lambda: _close_code(ws))
            ws.send(_ack(0, encoding))  # acknowledging from the first frame on
        except ConnectionClosed as exc:
            ws.close()
            raise _closed_by_server(exc, "watch") from exc
        except BaseException:
            ws.close()
            raise

    def recv(self, timeout: float | None = None) -> dict:
        """The next frame, after acknowledging the one returned before; with no ``timeout`` it
        waits as long as the session is idle."""
        from websockets.exceptions import ConnectionClosed

        try:
            if self._handled is not None:
                self.ws.send(_ack(self._handled, self.encoding))
                self._handled = None
            frame = _reply(self.ws.recv(timeout=timeout), self.encoding)
        except ConnectionClosed as exc:
            raise _closed_by_server(exc, "watch") from exc
        self._handled = frame["seq"]
        return frame

    def __iter__(self):
        while True:
            try:
                yield self.recv()
            except StreamError as exc:
                if exc.close_code == 1000:
                    return
                raise


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
        super().__init__(base_url, encoding, token, verify)
        self.timeout = timeout
        self.http = httpx.AsyncClient(
            base_url=self.base_url,
            timeout=timeout,
            headers=self.headers,
            limits=httpx.Limits(max_connections=max_connections),
            verify=self.tls if self.tls is not None else True,
        )

    async def _call(self, method: str, path: str, body=None):
        content = None if body is None else encode(body, self.encoding)
        return self._result(await self.http.request(method, path, content=content))

    async def health(self) -> dict:
        return await self._call("GET", "/health")

    async def models(self) -> list[dict]:
        return await self._call("GET", "/models")

    async def model(self, model: str) -> dict:
        return await self._call("GET", f"/models/{model}")

    async def mesh(self, model: str) -> dict:
        return await self._call("GET", f"/models/{model}/mesh")

    async def simulate(self, model: str, nodes, values, *, method: str = "network", E: float | None = None) -> dict:
        body = {
            "forces": {"nodes": np.asarray(nodes, np.int64), "values": np.asarray(values, np.float64)},
            "method": method,
            "E": E,
        }
        return await self._call("POST", f"/models/{model}/simulate", body)

    async def open_session(self, model: str, **config) -> AsyncSessionHandle:
        r = await self._call("POST", "/sessions", _config_body(model, config))
        return AsyncSessionHandle(self, r["session"], r["config"])

    async def _connect(self, url: str, max_size: int | None):
        """See :meth:`Client._connect`."""
        from websockets import connect
        from websockets.exceptions import InvalidStatus

        try:
            return await connect(url, open_timeout=self.timeout, **self._ws_options(max_size))
        except InvalidStatus as exc:
            raise _handshake_refused(exc) from None

    async def stream(self, model: str, *, max_size: int | None = 1 << 27, **config) -> AsyncStream:
        ws = await self._connect(_ws_url(self.base_url), max_size)
        stream = AsyncStream(ws, self.encoding, self.timeout)
        await stream._open(_config_body(model, config))
        return stream

    async def watch(self, session_id: str, *, max_size: int | None = 1 << 27) -> AsyncWatch:
        """Watch a session; see :meth:`Client.watch`."""
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
    def __init__(self, client: AsyncClient, session_id: str, config: dict) -> None:
        self.client = client
        self.id = session_id
        self.config = config

    async def frame(self, points, *, support=None, frame_id=None) -> dict:
        return await self.client._call("POST", f"/sessions/{self.id}/frames", _frame_body(points, support, frame_id))

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


class AsyncStream(_AsyncSocket):
    """A WebSocket stream (asyncio); see :class:`Stream`."""

    def __init__(self, ws, encoding: str, timeout: float | None = None) -> None:
        self.ws = ws
        self.encoding = encoding
        self.timeout = timeout
        self.session: str | None = None
        self.config: dict | None = None
        self._out_of_step = False

    async def _open(self, config: dict) -> None:
        import asyncio

        from websockets.exceptions import ConnectionClosed

        try:
            await self._send_raw(config)
            first = await asyncio.wait_for(self.ws.recv(), self.timeout)
            code = await _aclose_code(self.ws) if _is_error(first) else None
            self.session, self.config = _opened(first, lambda: code)
        except ConnectionClosed as exc:
            try:  # the server may have refused the handshake's token before the config was sent
                _reply(await asyncio.wait_for(self.ws.recv(), 0.5), self.encoding)
            except StreamError as refused:
                refused.close_code = _closed_code(exc)
                raise refused from None
            except Exception:
                pass
            raise _closed_by_server(exc) from exc
        except BaseException:
            await self.ws.close()
            raise

    async def _send_raw(self, body: dict) -> None:
        data = encode(body, self.encoding)
        await self.ws.send(data if self.encoding == "msgpack" else data.decode())

    async def send(self, points, *, support=None, frame_id=None) -> None:
        with _closes_as_stream_error():
            await self._send_raw(_frame_body(points, support, frame_id))

    async def recv(self, timeout: float | None = None) -> dict:
        import asyncio

        wait = timeout if timeout is not None else self.timeout
        with _closes_as_stream_error():
            message = await asyncio.wait_for(self.ws.recv(), wait)
        return _reply(message, self.encoding)

    async def frame(self, points, *, support=None, frame_id=None) -> dict:
        """As :meth:`Stream.frame`: after a reply that timed out, a StreamError (out of step)."""
        if self._out_of_step:
            raise StreamError(0, _OUT_OF_STEP)
        await self.send(points, support=support, frame_id=frame_id)
        try:
            return await self.recv()
        except TimeoutError:
            self._out_of_step = True
            raise


class AsyncWatch(_AsyncSocket):
    """A session's frames as it solves them (asyncio); see :class:`Watch`."""

    def __init__(self, ws, encoding: str, timeout: float | None = None) -> None:
        self.ws = ws
        self.encoding = encoding
        self.timeout = timeout  # for the first message only: a session may be idle for long
        self.session: str | None = None
        self.model: str | None = None
        self.config: dict | None = None
        self._handled: int | None = None

    async def _open(self) -> None:
        import asyncio

        from websockets.exceptions import ConnectionClosed

        try:
            hello = await asyncio.wait_for(self.ws.recv(), self.timeout)
            code = await _aclose_code(self.ws) if _is_error(hello) else None
            self.session, self.model, self.config = _watching(hello, lambda: code)
            await self.ws.send(_ack(0, self.encoding))
        except ConnectionClosed as exc:
            await self.ws.close()
            raise _closed_by_server(exc, "watch") from exc
        except BaseException:
            await self.ws.close()
            raise

    async def recv(self, timeout: float | None = None) -> dict:
        """As :meth:`Watch.recv`."""
        import asyncio

        from websockets.exceptions import ConnectionClosed

        try:
            if self._handled is not None:
                await self.ws.send(_ack(self._handled, self.encoding))
                self._handled = None
            frame = _reply(await asyncio.wait_for(self.ws.recv(), timeout), self.encoding)
        except ConnectionClosed as exc:
            raise _closed_by_server(exc, "watch") from exc
        self._handled = frame["seq"]
        return frame

    def __aiter__(self):
        return self

    async def __anext__(self) -> dict:
        try:
            return await self.recv()
        except StreamError as exc:
            if exc.close_code == 1000:
                raise StopAsyncIteration from None
            raise

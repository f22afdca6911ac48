"""Access (API.md, "Access"): bearer tokens on every endpoint but GET /health, over HTTP and the
WebSocket (handshake header or first message), sessions owned by their token, the Origin
allow-list, 415 for other content types, the open server's loopback-only rules, and TLS. All
against real servers on real ports, in JSON and MessagePack."""

from __future__ import annotations

import contextlib
import json
import logging
import socket
import ssl
import subprocess
import sys
import time

import httpx
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from clients import Client
from service.api.deps import check_token, fingerprint
from service.api.errors import ApiError
from service.api.server import BackgroundServer, BindRefused, check_bind, free_port
from service.config import Settings, read_token_file

from .conftest import MSGPACK, Live, mp, packed, recv, start, unpack, wait_for, ws_url

TOKEN_A = "alpha-token-0123456789abcdef"
TOKEN_B = "bravo-token-0123456789abcdef"
ORIGIN = "https://viewer.example"


def auth(token: str) -> dict:
    return {"authorization": f"Bearer {token}"}


@pytest.fixture(scope="module")
def guarded(bar_store, tmp_path_factory):
    """A server with two tokens (one from ELASTREG_API_TOKENS's form, one from a token file)
    and one allowed browser origin."""
    token_file = tmp_path_factory.mktemp("tokens") / "tokens.txt"
    token_file.write_text(f"# the second client\n{TOKEN_B}\n\n")
    server = start(
        bar_store[0], instance_id="guarded", api_tokens=TOKEN_A, token_file=token_file, allowed_origins=ORIGIN
    )
    yield Live(server)
    server.stop()


def close_code(ws) -> int:
    with pytest.raises(ConnectionClosed) as info:
        while True:
            ws.recv(timeout=10)
    return info.value.rcvd.code


# -- tokens over HTTP ----------------------------------------------------------------------------


def test_tokens_come_from_the_environment_form_and_a_file(guarded, tmp_path):
    assert guarded.settings.api_tokens == (TOKEN_A, TOKEN_B)
    assert TOKEN_A not in repr(guarded.settings)  # never in a log line
    assert read_token_file(guarded.settings.token_file) == (TOKEN_B,)
    with pytest.raises(ValueError, match="16 to 512"):
        Settings(store=tmp_path, api_tokens="short")
    assert check_token(guarded.settings, TOKEN_B) == fingerprint(TOKEN_B) != fingerprint(TOKEN_A)
    with pytest.raises(ApiError) as err:
        check_token(guarded.settings, "x" * 20)
    assert err.value.status == 401


def test_health_needs_no_token(guarded):
    r = httpx.get(guarded.url + "/health")
    assert r.status_code == 200 and r.json()["auth"] == "bearer" and r.json()["status"] == "ok"


ENDPOINTS = [
    ("GET", "/models", None),
    ("GET", "/models/bar", None),
    ("GET", "/models/bar/mesh", None),
    ("POST", "/models/bar/simulate", {"forces": {"nodes": [70], "values": [[0.0, 0.0, 1.0]]}}),
    ("POST", "/sessions", {"model": "bar"}),
    ("GET", "/sessions/guarded-xyz", None),
    ("POST", "/sessions/guarded-xyz/frames", {"points": [[0.0, 0.0, 0.0]]}),
    ("DELETE", "/sessions/guarded-xyz", None),
    ("GET", "/openapi.json", None),
    ("GET", "/models/bar/demo?frames=2&points=10", None),  # the viewer's demo: FEM work, a model's
    ("GET", "/models/nope/demo", None),  # not even which models exist
]


@pytest.mark.parametrize("method, path, body", ENDPOINTS)
@pytest.mark.parametrize("encoding", ["json", "msgpack"])
def test_every_endpoint_but_health_refuses_a_missing_or_unknown_token(guarded, method, path, body, encoding):
    media = "application/json" if encoding == "json" else "application/msgpack"
    content = None if body is None else (json.dumps(body).encode() if encoding == "json" else mp(body))
    with httpx.Client(base_url=guarded.url, headers={"content-type": media, "accept": media}) as c:
        for headers in (
            {},
            auth("unknown-token-0123456789"),
            {"authorization": f"Basic {TOKEN_A}"},
            {"authorization": "Bearer"},
        ):
            r = c.request(method, path, content=content, headers=headers)
            assert r.status_code == 401, (path, headers, r.status_code, r.text[:200])
            assert r.headers["www-authenticate"].startswith("Bearer")
            detail = r.json()["detail"] if encoding == "json" else unpack(r.content)["detail"]
            assert "token" in detail or "Bearer" in detail
        r = c.request(method, path, content=content, headers=auth(TOKEN_A))
        assert r.status_code != 401, (path, r.text[:200])


def test_docs_pages_are_off_and_the_schema_needs_a_token(guarded):
    assert httpx.get(guarded.url + "/docs").status_code == 404
    r = httpx.get(guarded.url + "/openapi.json", headers=auth(TOKEN_B))
    assert r.status_code == 200 and "/sessions" in r.json()["paths"]


def test_a_session_belongs_to_the_token_that_opened_it(guarded, support, clouds):
    a = httpx.Client(base_url=guarded.url, headers=auth(TOKEN_A), timeout=60)
    b = httpx.Client(base_url=guarded.url, headers={**auth(TOKEN_B), **MSGPACK}, timeout=60)
    with a, b:
        sid = a.post("/sessions", json={"model": "bar", "support": support.tolist()}).json()["session"]
        unknown = sid[:-4] + "zzzz"
        for method, path, content in [
            ("GET", f"/sessions/{sid}", None),
            ("POST", f"/sessions/{sid}/frames", mp({"points": packed(clouds[0])})),
            ("DELETE", f"/sessions/{sid}", None),
        ]:
            r = b.request(method, path, content=content)
            assert r.status_code == 404, (method, r.status_code)
            # exactly what a session that does not exist gets: nothing says it is someone else's
            other = b.request(method, path.replace(sid, unknown), content=content)
            assert unpack(r.content)["detail"].replace(sid, unknown) == unpack(other.content)["detail"]
        r = a.post(f"/sessions/{sid}/frames", json={"points": clouds[0].tolist()})
        assert r.status_code == 200 and a.get(f"/sessions/{sid}").json()["counters"]["frames"] == 1
        assert a.delete(f"/sessions/{sid}").status_code == 204


def test_one_token_cannot_take_every_session_slot(bar_store):
    """One token could open all max_sessions sessions and lock every other token out for
    session_ttl_s. With tokens, one holds at most max_sessions_per_token (half, here 2 of 4):
    over it a 503 with the session limit's Retry-After that names the per-token limit, over
    HTTP and the WebSocket, while another token still opens its own."""
    server = start(bar_store[0], instance_id="shared", api_tokens=f"{TOKEN_A},{TOKEN_B}", max_sessions=4)
    a = httpx.Client(base_url=server.url, headers=auth(TOKEN_A), timeout=60)
    b = httpx.Client(base_url=server.url, headers=auth(TOKEN_B), timeout=60)
    try:
        mine = [a.post("/sessions", json={"model": "bar"}) for _ in range(2)]
        assert [r.status_code for r in mine] == [201, 201]
        r = a.post("/sessions", json={"model": "bar"})
        assert r.status_code == 503 and r.headers.get("retry-after") == "5", r.text[:200]
        assert "this token holds its maximum of 2 sessions" in r.json()["detail"]
        assert "max_sessions_per_token" in r.json()["detail"]
        with connect(ws_url(Live(server)), additional_headers=auth(TOKEN_A)) as ws:
            ws.send(mp({"model": "bar"}))
            err = recv(ws)["error"]
            assert err["code"] == 503 and err["retry_after"] == 5 and "this token" in err["detail"]
            assert close_code(ws) == 1013
        assert [b.post("/sessions", json={"model": "bar"}).status_code for _ in range(2)] == [201, 201]
        assert a.delete(f"/sessions/{mine[0].json()['session']}").status_code == 204
        assert a.post("/sessions", json={"model": "bar"}).status_code == 201  # its slot came back
        assert httpx.get(server.url + "/health").json()["limits"]["max_sessions_per_token"] == 2
    finally:
        a.close()
        b.close()
        server.stop()


def test_the_client_sends_its_token_on_http_and_the_websocket(guarded, support, clouds):
    with Client(guarded.url, token=TOKEN_A) as api:
        assert [m["id"] for m in api.models()] == ["bar"]
        with api.stream("bar", support=support) as s:
            assert s.frame(clouds[0])["displacement"].shape == (81, 3)
    with Client(guarded.url) as api, pytest.raises(Exception) as err:
        api.models()
    assert getattr(err.value, "status", None) == 401


# -- tokens on the WebSocket ---------------------------------------------------------------------


def test_websocket_token_in_the_handshake_header(guarded, support, clouds):
    with connect(ws_url(guarded), additional_headers=auth(TOKEN_A)) as ws:
        ws.send(mp({"model": "bar", "support": packed(support, "<i8")}))
        opened = recv(ws)
        ws.send(mp({"points": packed(clouds[1]), "frame_id": 1}))
        assert recv(ws)["frame_id"] == 1
        sid = opened["session"]
        # the stream's session is its token's: another token is told it does not exist
        assert httpx.get(f"{guarded.url}/sessions/{sid}", headers=auth(TOKEN_B)).status_code == 404
        assert httpx.get(f"{guarded.url}/sessions/{sid}", headers=auth(TOKEN_A)).status_code == 200


def test_a_handshake_token_is_compared_once_per_socket(guarded, support, clouds, monkeypatch):
    """Admission, the accept and the first message each compared the header's token with the
    server's (three constant-time checks of one token): the verdict of admission's one check now
    travels with the socket. Counted on hmac.compare_digest, against one check_token's count."""
    import hmac

    from service.api.deps import check_token

    compared = 0
    compare = hmac.compare_digest

    def counted(a, b):
        nonlocal compared
        compared += 1
        return compare(a, b)

    monkeypatch.setattr(hmac, "compare_digest", counted)
    check_token(guarded.settings, TOKEN_B)
    one_check, compared = compared, 0
    assert one_check >= 1
    with connect(ws_url(guarded), additional_headers=auth(TOKEN_B)) as ws:
        ws.send(mp({"model": "bar", "support": packed(support, "<i8")}))
        assert "session" in recv(ws)
        ws.send(mp({"points": packed(clouds[1]), "frame_id": 1}))
        assert recv(ws)["frame_id"] == 1
    assert compared == one_check, f"{compared // one_check} checks of the handshake's token"


@pytest.mark.parametrize("binary", [False, True])
def test_websocket_token_in_the_first_message(guarded, support, clouds, binary):
    """What a browser does (it cannot set headers): the token rides in the session config."""
    config = {"model": "bar", "support": support.tolist(), "token": TOKEN_B}
    with connect(ws_url(guarded)) as ws:
        ws.send(mp(config) if binary else json.dumps(config))
        opened = recv(ws)
        assert "token" not in opened["config"] and opened["session"].startswith("guarded-")
        ws.send(json.dumps({"points": clouds[2].tolist(), "frame_id": "x"}))
        assert recv(ws)["frame_id"] == "x"


@pytest.mark.parametrize(
    "headers, first",
    [
        ({}, {"model": "bar"}),  # no token anywhere
        ({}, {"model": "bar", "token": "unknown-token-0123456789"}),
        ({}, {"model": "bar", "token": 12345}),
    ],
)
def test_websocket_without_a_valid_token_closes_with_1008(guarded, headers, first):
    registry = guarded.app.state.registry
    before = set(registry._held)  # the ids, not a count: an earlier test's stream may still be closing
    with connect(ws_url(guarded), additional_headers=headers) as ws:
        ws.send(json.dumps(first))
        r = recv(ws)
        assert r["error"]["code"] == 401
        assert close_code(ws) == 1008
    assert not set(registry._held) - before  # nothing was opened for it


@pytest.mark.parametrize("asynchronous", [False, True])
def test_the_client_reports_a_handshake_tokens_401(guarded, asynchronous):
    """The server refuses an unknown handshake token before the client sends its config: the
    client's StreamError still carries the 401, not a bare "closed" (10 tries: it raced)."""
    import asyncio

    from clients import AsyncClient, StreamError

    async def open_async() -> StreamError:
        async with AsyncClient(guarded.url, token="unknown-token-0123456789") as api:
            with pytest.raises(StreamError) as info:
                await api.stream("bar")
            return info.value

    def open_sync() -> StreamError:
        with Client(guarded.url, token="unknown-token-0123456789") as api, pytest.raises(StreamError) as info:
            api.stream("bar")
        return info.value

    for _ in range(10):
        err = asyncio.run(open_async()) if asynchronous else open_sync()
        assert err.status == 401 and "unknown token" in str(err.detail)


def test_a_bad_handshake_token_is_refused_before_any_message(guarded):
    """(and a good token in a first message would not rescue it: none is read)"""
    t0 = time.monotonic()
    with connect(ws_url(guarded), additional_headers=auth("unknown-token-0123456789")) as ws:
        assert recv(ws)["error"]["code"] == 401
        assert close_code(ws) == 1008
    assert time.monotonic() - t0 < guarded.settings.first_message_timeout_s


# -- browsers ------------------------------------------------------------------------------------


def test_unlisted_origins_are_refused_listed_and_same_origin_ones_pass(guarded):
    h = auth(TOKEN_A)
    evil = httpx.post(guarded.url + "/sessions", json={"model": "bar"}, headers={**h, "origin": "https://evil.example"})
    assert evil.status_code == 403 and "evil.example" in evil.json()["detail"]
    assert httpx.get(guarded.url + "/health", headers={"origin": "null"}).status_code == 403
    ok = httpx.get(guarded.url + "/models", headers={**h, "origin": ORIGIN})
    assert ok.status_code == 200 and ok.headers["access-control-allow-origin"] == ORIGIN
    pre = httpx.options(
        guarded.url + "/sessions",
        headers={
            "origin": ORIGIN,
            "access-control-request-method": "POST",
            "access-control-request-headers": "authorization, content-type",
        },
    )
    assert pre.status_code == 200 and "authorization" in pre.headers["access-control-allow-headers"].lower()
    pre = httpx.options(
        guarded.url + "/sessions", headers={"origin": "https://evil.example", "access-control-request-method": "POST"}
    )
    assert pre.status_code == 403
    same = httpx.get(guarded.url + "/models", headers={**h, "origin": guarded.url})
    assert same.status_code == 200


def test_websocket_handshakes_from_unlisted_origins_are_refused(guarded):
    with pytest.raises(InvalidStatus) as err:
        connect(ws_url(guarded), origin="https://evil.example", additional_headers=auth(TOKEN_A))
    assert err.value.response.status_code == 403
    with connect(ws_url(guarded), origin=ORIGIN, additional_headers=auth(TOKEN_A)) as ws:
        ws.send(json.dumps({"model": "bar"}))
        assert "session" in recv(ws)


@pytest.mark.parametrize(
    "headers",
    [
        {"content-type": "text/plain"},
        {},
        {"content-type": "application/x-www-form-urlencoded"},
        {"content-type": "multipart/form-data; boundary=x"},
    ],
)
def test_bodies_a_page_can_send_without_a_preflight_are_415(live, http, headers):
    """On the open test server too: a text/plain body of valid JSON is not taken as JSON."""
    body = json.dumps({"model": "bar"}).encode()
    r = httpx.post(live.url + "/sessions", content=body, headers=headers)
    assert r.status_code == 415, (headers, r.status_code)
    assert "Content-Type" in r.json()["detail"]
    assert live.app.state.registry.counts()["http"] == http.get("/health").json()["sessions"]["http"]


def test_an_open_server_answers_loopback_names_only(live):
    """DNS rebinding: a page's own name that resolves to 127.0.0.1 makes its requests
    same-origin; a server without tokens answers loopback host names only."""
    r = httpx.get(live.url + "/health", headers={"host": "rebound.example:80"})
    assert r.status_code == 403 and "loopback" in r.json()["detail"]
    assert httpx.get(live.url + "/health", headers={"host": f"localhost:{live.server.port}"}).status_code == 200
    sock = socket.create_connection(("127.0.0.1", live.server.port))
    with pytest.raises(InvalidStatus) as err:  # the handshake's Host is the URI's
        connect("ws://rebound.example/stream", sock=sock)
    assert err.value.response.status_code == 403
    sock.close()


# -- an open server ------------------------------------------------------------------------------


def test_an_open_server_says_so_and_binds_loopback_only(bar_store, caplog, tmp_path):
    open_settings = Settings(store=bar_store[0], blas_threads=0)
    for host in ("0.0.0.0", "::", "10.1.2.3", "theatre-pc.local"):
        with pytest.raises(BindRefused, match="without tokens"):
            check_bind(host, open_settings)
    for host in ("127.0.0.1", "::1", "localhost"):
        check_bind(host, open_settings)
    check_bind("0.0.0.0", Settings(store=tmp_path, insecure=True))
    check_bind("0.0.0.0", Settings(store=tmp_path, api_tokens=TOKEN_A))
    with caplog.at_level(logging.WARNING, logger="service.api.app"):
        with BackgroundServer(open_settings):
            pass
    assert any("NO TOKENS" in r.getMessage() for r in caplog.records)


def test_serve_refuses_a_network_address_without_tokens(bar_store):
    port = free_port()
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "service.cli",
            "serve",
            "--store",
            str(bar_store[0]),
            "--host",
            "0.0.0.0",
            "--port",
            str(port),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode != 0 and "refusing to serve 0.0.0.0 without tokens" in r.stderr
    r = subprocess.run(
        [sys.executable, "-m", "service.cli", "serve", "--store", str(bar_store[0]), "--ssl-certfile", "cert.pem"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode != 0 and "go together" in r.stderr


# -- TLS -----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def certificate(tmp_path_factory):
    """A self-signed certificate for 127.0.0.1, made here with the openssl command."""
    folder = tmp_path_factory.mktemp("tls")
    cert, key = folder / "cert.pem", folder / "key.pem"
    subprocess.run(
        [
            "openssl",
            "req",
            "-x509",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-days",
            "1",
            "-subj",
            "/CN=127.0.0.1",
            "-addext",
            "subjectAltName=IP:127.0.0.1",
            "-keyout",
            str(key),
            "-out",
            str(cert),
        ],
        check=True,
        capture_output=True,
        timeout=60,
    )
    return cert, key


def test_https_and_wss_with_a_certificate(bar_store, certificate, support, clouds):
    cert, key = certificate
    settings = Settings(
        store=bar_store[0],
        blas_threads=0,
        api_tokens=TOKEN_A,
        max_body_bytes=1 << 20,
        max_message_bytes=1 << 20,
        max_points=3000,
    )
    with BackgroundServer(settings, ssl_certfile=str(cert), ssl_keyfile=str(key)) as server:
        assert server.url.startswith("https://")
        context = ssl.create_default_context(cafile=str(cert))
        r = httpx.get(server.url + "/health", verify=context)
        assert r.status_code == 200 and r.json()["status"] == "ok"
        with pytest.raises(httpx.HTTPError):  # a client that does not trust it refuses it
            httpx.get(server.url + "/health")
        with pytest.raises(httpx.HTTPError):  # and plain HTTP is not served on that port
            httpx.get(server.url.replace("https://", "http://") + "/health")
        with Client(server.url, token=TOKEN_A, verify=cert) as api:  # HTTPS and WSS; a path's CA file
            assert api.model("bar")["id"] == "bar"
            with api.stream("bar", support=support) as s:
                result = s.frame(clouds[0])
            assert np.isfinite(result["displacement"]).all()
        with pytest.raises(ValueError, match="verify must be"):  # not silently the system's CAs
            Client(server.url, token=TOKEN_A, verify=False)


# -- watching needs the session's token ----------------------------------------------------------


def _watch_url(live: Live, sid: str) -> str:
    return live.url.replace("http://", "ws://") + f"/sessions/{sid}/watch"


def _guarded_session(guarded, support, token: str) -> str:
    r = httpx.post(f"{guarded.url}/sessions", json={"model": "bar", "support": support.tolist()}, headers=auth(token))
    assert r.status_code == 201, r.text
    return r.json()["session"]


@pytest.mark.parametrize("how", ["header", "first message"])
def test_a_watcher_with_the_sessions_token_sees_its_frames(guarded, support, clouds, how):
    sid = _guarded_session(guarded, support, TOKEN_A)
    headers = auth(TOKEN_A) if how == "header" else {}
    with connect(_watch_url(guarded, sid), additional_headers=headers) as ws:
        if how == "first message":
            ws.send(json.dumps({"token": TOKEN_A}))
        assert recv(ws)["watching"] == sid
        r = httpx.post(
            f"{guarded.url}/sessions/{sid}/frames",
            json={"points": clouds[1].tolist(), "frame_id": 7},
            headers=auth(TOKEN_A),
        )
        assert r.status_code == 200
        assert recv(ws)["result"]["frame_id"] == 7


@pytest.mark.parametrize(
    "headers, first, code",
    [
        ({}, {"token": TOKEN_B}, 404),  # another token's session: as if it did not exist
        (auth(TOKEN_B), None, 404),
        ({}, {}, 401),  # no token at all
        ({}, {"token": "unknown-token-0123456789"}, 401),
    ],
)
def test_a_watcher_without_the_sessions_token_is_refused(guarded, support, headers, first, code):
    sid = _guarded_session(guarded, support, TOKEN_A)
    with connect(_watch_url(guarded, sid), additional_headers=headers) as ws:
        if first is not None:
            ws.send(json.dumps(first))
        assert recv(ws)["error"]["code"] == code
        assert close_code(ws) == 1008


def test_a_silent_watcher_on_a_guarded_server_is_closed_with_1008(bar_store):
    """A browser sends the watch's token in its first message: one that sends nothing within
    the first-message timeout gets a 401 and a 1008 close, as /stream's silent client does."""
    server = start(bar_store[0], instance_id="silent", api_tokens=TOKEN_A, first_message_timeout_s=0.5)
    try:
        url = server.url.replace("http://", "ws://") + "/sessions/silent-xyz/watch"
        with connect(url) as ws:
            r = recv(ws)
            assert r["error"]["code"] == 401 and "no token within 0.5 s" in r["error"]["detail"]
            with pytest.raises(ConnectionClosed) as info:
                ws.recv(timeout=10)
            assert info.value.rcvd is not None and info.value.rcvd.code == 1008
    finally:
        server.stop()


@pytest.mark.parametrize("workers", ["1", "2"])
def test_serve_refuses_a_missing_or_mismatched_certificate_before_it_starts(bar_store, certificate, tmp_path, workers):
    """With workers, uvicorn's children died on it and were respawned for ever; with one, a
    traceback that did not name the file."""
    cert, _ = certificate
    other = tmp_path / "other.pem"
    subprocess.run(
        ["openssl", "genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", str(other)],
        check=True, capture_output=True,
    )  # fmt: skip
    for certfile, keyfile, words in ((tmp_path / "nope.pem", other, "no such file"), (cert, other, "private key")):
        r = subprocess.run(
            [sys.executable, "-m", "service.cli", "serve", "--store", str(bar_store[0]), "--port", str(free_port()),
             "--workers", workers, "--ssl-certfile", str(certfile), "--ssl-keyfile", str(keyfile)],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip
        assert r.returncode != 0 and words in r.stderr and str(certfile) in r.stderr, r.stderr[-500:]


def test_another_token_cannot_tell_a_closed_session_from_one_that_never_was(guarded, support):
    """deployment.md: another token gets the same 404 as for a session that never existed; what
    became of a closed session is its own token's to know, over HTTP and on the watch."""
    sid = _guarded_session(guarded, support, TOKEN_A)
    assert httpx.delete(f"{guarded.url}/sessions/{sid}", headers=auth(TOKEN_A)).status_code == 204
    never = sid[:-4] + ("aaaa" if not sid.endswith("aaaa") else "bbbb")

    def told(token: str, session: str) -> tuple[str, str]:
        r = httpx.get(f"{guarded.url}/sessions/{session}", headers=auth(token))
        assert r.status_code == 404
        with connect(_watch_url(guarded, session), additional_headers=auth(token)) as ws:
            watch = recv(ws)["error"]
        assert watch["code"] == 404
        return r.json()["detail"].replace(session, "ID"), watch["detail"].replace(session, "ID")

    assert told(TOKEN_B, sid) == told(TOKEN_B, never)
    assert all("closed" in d for d in told(TOKEN_A, sid))  # its own token is told what happened


# -- sockets without a token cannot take the slots of clients with one ----------------------------


def test_sockets_without_a_token_cannot_lock_out_clients_with_one(bar_store, support, clouds):
    """(review s25, probe_slots.py) Token-less sockets that send nothing held every one of
    max_sockets for first_message_timeout_s: a client with a valid token got 503s. They now
    count against max_tokenless_sockets, apart, and move to max_sockets once their token comes."""
    server = start(
        bar_store[0],
        instance_id="squat",
        api_tokens=TOKEN_A,
        max_sockets=2,
        max_tokenless_sockets=2,
        first_message_timeout_s=60.0,
    )
    live = Live(server)
    url = ws_url(live)
    with contextlib.ExitStack() as held:
        held.callback(server.stop)
        squatters = [held.enter_context(connect(url)) for _ in range(2)]  # no token, nothing sent
        # clients with the token still get in, all of max_sockets of them, stream and watcher alike
        with Client(live.url, token=TOKEN_A) as api, api.stream("bar", support=support.tolist()) as stream:
            assert stream.frame(clouds[0], frame_id=1)["frame_id"] == 1
            with connect(_watch_url(live, stream.session), additional_headers=auth(TOKEN_A)) as watcher:
                assert recv(watcher)["watching"] == stream.session
                assert server.app.state.sockets == 2
                # a token-less socket whose first message brings the token finds max_sockets full:
                # a 503 it may retry, and a close with 1013
                squatters[0].send(json.dumps({"model": "bar", "token": TOKEN_A}))
                refused = recv(squatters[0])["error"]
                assert refused["code"] == 503 and refused["retry_after"] == 1
                assert "maximum of 2 open WebSockets" in refused["detail"]
                assert close_code(squatters[0]) == 1013
        assert wait_for(lambda: server.app.state.sockets == 0 and server.app.state.tokenless_sockets == 1)
        held.enter_context(connect(url))  # the refused one's place is free again; the cap holds
        with pytest.raises(InvalidStatus) as err:
            connect(url)
        assert err.value.response.status_code == 503 and err.value.response.headers["retry-after"] == "1"
        assert b"maximum of 2 WebSockets waiting for a token" in err.value.response.body
        # with room, a first message's token moves its socket to max_sockets: its place among
        # the token-less ones is free for the next
        squatters[1].send(json.dumps({"model": "bar", "token": TOKEN_A}))
        assert "session" in recv(squatters[1])
        held.enter_context(connect(url))
        health = httpx.get(live.url + "/health").json()
        assert health["sockets"] == 1 and health["tokenless_sockets"] == 2

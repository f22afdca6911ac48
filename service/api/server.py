"""``elastreg serve``: the API on uvicorn, one process or several.

With ``workers > 1`` uvicorn runs that many processes on one socket, each building its own app
(its own models, pool, sessions and instance id) through the :func:`~.app.create_app` factory.
A WebSocket stream is served whole by the process that accepted it; an HTTP session lives in
the process that opened it, so its requests must reach that process (see docs/deployment.md).

What uvicorn offers is used for the transport's limits (message size, keepalive pings,
connections in progress, the graceful-shutdown timeout) and for TLS. A server without tokens
refuses to bind beyond loopback unless told ``insecure``, and ``serve`` refuses a store that is
not a folder it can read. On SIGTERM or Ctrl-C the one-process
server drains first (:func:`~.app.drain`): solves in flight finish and are answered, the rest
get 503, streams close with 1012; then uvicorn closes its connections.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
from typing import Any

from ..config import Settings, get_settings, setting_problems

log = logging.getLogger(__name__)


class BindRefused(RuntimeError):
    """A non-loopback address asked of a server without tokens."""


def check_bind(host: str, settings: Settings) -> None:
    """Refuse to serve a network without tokens unless ``insecure`` is set (API.md, "Access")."""
    from .guard import is_loopback

    if settings.api_tokens or settings.insecure or is_loopback(host):
        return
    raise BindRefused(
        f"refusing to serve {host} without tokens: anyone on that network could open, read and close "
        "sessions. Set ELASTREG_API_TOKENS or --token-file (see docs/deployment.md), or pass --insecure "
        "on a network you trust"
    )


def uvicorn_options(settings: Settings) -> dict:
    """The uvicorn settings that carry the service's limits."""
    return dict(
        ws_max_size=settings.max_message_bytes,
        ws_ping_interval=settings.ws_ping_interval_s,
        ws_ping_timeout=settings.ws_ping_timeout_s,
        ws_per_message_deflate=False,  # a compressed message's size is not its cost: no deflate bombs
        limit_concurrency=settings.max_connections,
        timeout_graceful_shutdown=math.ceil(settings.drain_timeout_s) + 1,
        h11_max_incomplete_event_size=64 << 10,  # request line and headers
        access_log=settings.access_log,
    )


def _draining_server(config, app):
    import uvicorn

    from .app import drain

    class DrainingServer(uvicorn.Server):
        """uvicorn's server, which lets the app finish its frames before it closes connections."""

        async def startup(self, sockets=None) -> None:
            await super().startup(sockets)
            if sockets and self.started:  # uvicorn says where it listens only for sockets it bound
                self._log_started_message(sockets)

        async def shutdown(self, sockets=None) -> None:
            for server in self.servers:  # no new connections while the frames in flight finish
                server.close()
            await drain(app, app.state.settings.drain_timeout_s)
            await super().shutdown(sockets)

    return DrainingServer(config)


def serve(
    store=None,
    host: str = "127.0.0.1",
    port: int = 8000,
    workers: int = 1,
    *,
    token_file=None,
    insecure: bool = False,
    ssl_certfile=None,
    ssl_keyfile=None,
) -> None:
    """Run the server until interrupted. ``store`` overrides ELASTREG_STORE; ``token_file`` and
    ``insecure`` override ELASTREG_TOKEN_FILE and ELASTREG_INSECURE (set in the environment, so
    that worker processes read them too)."""
    import uvicorn

    if store is not None:
        os.environ["ELASTREG_STORE"] = str(store)  # worker processes read it too
    if token_file is not None:
        os.environ["ELASTREG_TOKEN_FILE"] = str(token_file)
    if insecure:
        os.environ["ELASTREG_INSECURE"] = "1"
    get_settings.cache_clear()
    from pydantic import ValidationError

    try:
        settings = get_settings()  # refuses bad settings here, before any process starts
    except ValidationError as exc:
        raise SystemExit("\n".join(f"error: {line}" for line in setting_problems(exc))) from None
    try:
        check_bind(host, settings)
    except BindRefused as exc:
        raise SystemExit(f"error: {exc}") from None
    from ..store import StoreError, check_store

    try:  # a missing or mistyped store is an error here, not a server that can serve nothing
        check_store(settings.store)
    except StoreError as exc:
        raise SystemExit(f"error: {exc}; check --store or ELASTREG_STORE") from None
    if bool(ssl_certfile) != bool(ssl_keyfile):
        raise SystemExit("error: --ssl-certfile and --ssl-keyfile go together")
    if ssl_certfile:  # here, before any worker starts: uvicorn's workers would die and respawn for ever
        check_certificate(ssl_certfile, ssl_keyfile)
    # bound before the models load and warm (seconds): a port in use is one line at once
    sock = listening_socket(host, port)
    common: dict[str, Any] = dict(
        host=host,
        port=port,
        log_level="info",  # uvicorn's own lines (where it listens); access lines per settings
        ssl_certfile=ssl_certfile,
        ssl_keyfile=ssl_keyfile,
        **uvicorn_options(settings),
    )
    if workers > 1:
        log.warning(
            "%d worker processes: an HTTP session's requests must reach the process that opened it "
            "(WebSocket streams are fine); no drain at shutdown. See docs/deployment.md",
            workers,
        )
        sock.close()  # uvicorn's supervisor binds its own, for its workers to share
        uvicorn.run("service.api.app:create_app", factory=True, workers=workers, **common)
    else:
        from .app import create_app

        app = create_app(settings)
        config = uvicorn.Config(app, **common)
        with contextlib.suppress(KeyboardInterrupt):  # Ctrl-C: drained and stopped, no traceback (uvicorn.run's way)
            _draining_server(config, app).run(sockets=[sock])


def listening_socket(host: str, port: int):
    """A TCP socket bound to (host, port), as uvicorn binds one; SystemExit in one line when
    the address cannot be taken (a port in use, a host this machine does not have)."""
    import socket

    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        raise SystemExit(f"error: cannot listen on {host}:{port} ({exc.strerror or exc})") from None
    sock.set_inheritable(True)
    return sock


def check_certificate(certfile: str, keyfile: str | None) -> None:
    """SystemExit naming the file when the certificate and its key cannot serve TLS."""
    import ssl

    for path in (certfile, keyfile):
        if path and not os.path.isfile(path):
            raise SystemExit(f"error: {path}: no such file (--ssl-certfile / --ssl-keyfile)")
    try:
        ssl.create_default_context(ssl.Purpose.CLIENT_AUTH).load_cert_chain(certfile, keyfile)
    except (ssl.SSLError, OSError, ValueError) as exc:
        raise SystemExit(f"error: {certfile} with {keyfile}: not a certificate and its private key ({exc})") from None


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port nobody listens on right now."""
    import socket

    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class BackgroundServer:
    """The API served by uvicorn in a background thread on a free loopback port, for the demo,
    the benchmarks and the tests (a real server: real sockets, real WebSockets, TLS when given
    a certificate and its key).

    >>> with BackgroundServer(Settings(store=path)) as server:   # doctest: +SKIP
    ...     Client(server.url).health()
    """

    def __init__(
        self,
        settings=None,
        *,
        host: str = "127.0.0.1",
        port: int | None = None,
        log_level: str = "warning",
        startup_timeout: float = 120.0,
        ssl_certfile=None,
        ssl_keyfile=None,
    ) -> None:
        import uvicorn

        from .app import create_app

        self.settings = settings or get_settings()
        check_bind(host, self.settings)
        self.app = create_app(self.settings)
        self.host = host
        self.port = port or free_port(host)
        self.tls = ssl_certfile is not None
        self.startup_timeout = startup_timeout
        options = {**uvicorn_options(self.settings), "access_log": False}
        config = uvicorn.Config(
            self.app,
            host=host,
            port=self.port,
            log_level=log_level,
            lifespan="on",
            ssl_certfile=ssl_certfile,
            ssl_keyfile=ssl_keyfile,
            **options,
        )
        self.server = _draining_server(config, self.app)
        self.thread = None

    @property
    def url(self) -> str:
        return f"{'https' if self.tls else 'http'}://{self.host}:{self.port}"

    def start(self) -> BackgroundServer:
        import threading
        import time

        failed: list[str] = []

        def run() -> None:
            try:
                self.server.run()
            except SystemExit:  # uvicorn's way out of a failed start-up (a bind, the lifespan)
                failed.append("uvicorn exited: its log above says why")

        self.thread = threading.Thread(target=run, name="elastreg-server", daemon=True)
        self.thread.start()
        deadline = time.monotonic() + self.startup_timeout
        try:
            while not self.server.started:
                if not self.thread.is_alive():
                    why = failed[0] if failed else "see the log"
                    raise RuntimeError(f"the server stopped during start-up ({why})")
                if time.monotonic() > deadline:
                    raise RuntimeError(f"the server did not start within {self.startup_timeout:g} s")
                time.sleep(0.02)
        except BaseException:  # Ctrl-C (or a timeout) while it starts: stopped, not left running
            self.stop()  # (a context manager's __exit__ never runs when __enter__ raised)
            raise
        return self

    def stop(self) -> None:
        self.server.should_exit = True
        if self.thread is not None:
            self.thread.join(timeout=30 + self.settings.drain_timeout_s)

    def __enter__(self) -> BackgroundServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

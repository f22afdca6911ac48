"""``elastreg serve``: the API on uvicorn, one process or several.

With ``workers > 1`` uvicorn runs that many processes on one socket, each building its own app
(its own models, pool, sessions and instance id) through the :func:`~.app.create_app` factory.
A WebSocket stream is served whole by the process that accepted it; an HTTP session lives in
the process that opened it, so its requests must reach that process (see the README).
"""

from __future__ import annotations

import logging
import os
from typing import Any

from ..config import get_settings

log = logging.getLogger(__name__)


def serve(store=None, host: str = "127.0.0.1", port: int = 8000, workers: int = 1) -> None:
    """Run the server until interrupted. ``store`` overrides ELASTREG_STORE."""
    import uvicorn

    if store is not None:
        os.environ["ELASTREG_STORE"] = str(store)  # worker processes read it too
        get_settings.cache_clear()
    from pydantic import ValidationError

    try:
        settings = get_settings()  # refuses bad settings here, before any process starts
    except ValidationError as exc:
        raise SystemExit(f"error: invalid ELASTREG_* settings:\n{exc}") from None
    common: dict[str, Any] = dict(
        host=host,
        port=port,
        ws_max_size=settings.max_body_bytes,
        access_log=settings.access_log,
        log_level="info",  # uvicorn's own lines (where it listens); access lines per settings
    )
    if workers > 1:
        uvicorn.run("service.api.app:create_app", factory=True, workers=workers, **common)
    else:
        from .app import create_app

        uvicorn.run(create_app(settings), **common)


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port nobody listens on right now."""
    import socket

    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class BackgroundServer:
    """The API served by uvicorn in a background thread on a free loopback port, for the demo,
    the benchmarks and the tests (a real server: real sockets, real WebSockets).

    >>> with BackgroundServer(Settings(store=path)) as server:   # doctest: +SKIP
    ...     Client(server.url).health()
    """

    def __init__(self, settings=None, *, host: str = "127.0.0.1", port: int | None = None,
                 log_level: str = "warning", startup_timeout: float = 120.0) -> None:
        import uvicorn

        from .app import create_app

        self.settings = settings or get_settings()
        self.app = create_app(self.settings)
        self.host = host
        self.port = port or free_port(host)
        self.startup_timeout = startup_timeout
        config = uvicorn.Config(
            self.app, host=host, port=self.port, log_level=log_level, access_log=False,
            ws_max_size=self.settings.max_body_bytes, lifespan="on",
        )
        self.server = uvicorn.Server(config)
        self.thread = None

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def start(self) -> BackgroundServer:
        import threading
        import time

        self.thread = threading.Thread(target=self.server.run, name="elastreg-server", daemon=True)
        self.thread.start()
        deadline = time.monotonic() + self.startup_timeout
        while not self.server.started:
            if not self.thread.is_alive():
                raise RuntimeError("the server stopped during start-up (see the log)")
            if time.monotonic() > deadline:
                raise RuntimeError(f"the server did not start within {self.startup_timeout:g} s")
            time.sleep(0.02)
        return self

    def stop(self) -> None:
        self.server.should_exit = True
        if self.thread is not None:
            self.thread.join(timeout=30)

    def __enter__(self) -> BackgroundServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

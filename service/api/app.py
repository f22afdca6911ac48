"""The FastAPI application: ``create_app(settings)`` assembles middleware, handlers and routers;
its lifespan opens the model store and holds what requests share (app.state): the models, the
session registry with its sweeper, the solve pool, the open WebSockets and streams.

Access: every router but /health's is included with the token dependency (:func:`.deps.owner`);
WebSocket routes call :func:`.deps.authorize_websocket` themselves. On a server with tokens the
OpenAPI document needs one too, and the interactive docs (which cannot send one) are off.

Run it with ``elastreg serve`` (:mod:`.server`), or ``uvicorn --factory service.api.app:create_app``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time

from fastapi import Depends, FastAPI
from fastapi.openapi.utils import get_openapi
from fastapi.responses import JSONResponse
from starlette.middleware.cors import CORSMiddleware

from .. import __version__
from ..config import Settings, get_settings, limit_threads
from . import deps, errors
from .guard import OriginGuard
from .memo import Memo
from .routes import health, models, sessions, stream, viewer, watch
from .schemas.models import SimulateIn
from .schemas.sessions import FrameIn, SessionCreate
from .sessions import SessionRegistry
from .work import SolvePool
from .wsend import KeepTransport

log = logging.getLogger(__name__)

#: the bodies the routes validate themselves, not through FastAPI: the OpenAPI schema adds them
REQUEST_MODELS = (SessionCreate, FrameIn, SimulateIn)


def _warm_up(entries: dict) -> None:
    """Do now what a session's first frame would otherwise wait for (docs/performance.md): the
    distance kernel compiled (or loaded), and each model's error estimator made, its rest
    stiffness factorised, and run once at rest (its compiled kernels loaded: the demo's first
    frame 356-577 -> 47-59 ms)."""
    import numpy as np

    from ..registration.confidence import estimator_for
    from ..registration.distance import PointToSurface

    PointToSurface(np.array([[0, 1, 2]]))
    for entry in entries.values():
        for model in (entry.network, entry.fem):
            try:
                estimator_for(model).forward_error(
                    np.zeros((model.mesh.n_nodes, 3)), np.zeros((0, 3)), np.zeros(0, int)
                )
            except Exception as exc:  # the other models stay warmed; this one's frames meet the error
                log.warning("model %s: its error estimator could not be made (%s)", entry.id, exc)


async def _sweep(registry: SessionRegistry, every: float) -> None:
    while True:
        await asyncio.sleep(every)
        gone = registry.expire()
        if gone:
            log.info("expired %d idle session(s)", len(gone))


@contextlib.asynccontextmanager
async def lifespan(app: FastAPI):
    from ..store import open_store

    settings: Settings = app.state.settings
    entries, refused = await asyncio.to_thread(open_store, settings.store)
    if settings.blas_threads:
        limit_threads(settings.blas_threads)
    t0 = time.perf_counter()
    await asyncio.to_thread(_warm_up, entries)
    log.info(
        "instance %s: %d model(s) from %s (%d refused), warmed in %.1f s",
        settings.instance_id,
        len(entries),
        settings.store,
        len(refused),
        time.perf_counter() - t0,
    )
    if not entries:
        log.error("no model loaded from %s: /health reports degraded (503)", settings.store)
    if settings.api_tokens:
        log.info("access: %d bearer token(s) required on every endpoint but GET /health", len(settings.api_tokens))
    else:
        log.warning(
            "access: NO TOKENS - this server is open to anyone who can reach it (set "
            "ELASTREG_API_TOKENS or --token-file before it leaves loopback)"
        )
    app.state.models = entries
    app.state.store_errors = refused
    app.state.mesh_cache = Memo(2 * max(len(entries), 1))  # each model's mesh in two encodings
    app.state.demo_sequences = Memo(viewer.DEMO_CACHE)
    app.state.registry = SessionRegistry(
        max_sessions=settings.max_sessions,
        ttl_s=settings.session_ttl_s,
        instance_id=settings.instance_id,
        retry_after=settings.session_retry_after_s,
        max_per_owner=settings.max_sessions_per_token,
    )
    app.state.pool = SolvePool(settings.solver_threads, settings.solve_queue, retry_after=settings.retry_after_s)
    app.state.sockets = 0  # open WebSockets against max_sockets (sockets.websocket_slot)
    app.state.tokenless_sockets = 0  # and those waiting for their first message's token
    app.state.streams = set()  # running /stream runners, told to drain at shutdown
    sweeper = asyncio.create_task(_sweep(app.state.registry, settings.sweep_interval_s))
    try:
        yield
    finally:
        sweeper.cancel()
        app.state.pool.shutdown()


async def drain(app: FastAPI, timeout: float) -> bool:
    """Before the server closes its connections: refuse new solves (503), let the ones in flight
    finish and their replies go out, and close each stream with 1012 once it has answered what
    it had queued. True when everything finished within ``timeout`` seconds."""
    state = app.state
    if not hasattr(state, "pool"):  # never started
        return True
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    state.pool.draining = True
    n_streams, n_jobs = len(state.streams), state.pool.in_flight
    for runner in list(state.streams):
        runner.drain()
    while (state.streams or state.pool.in_flight) and loop.time() < deadline:
        await asyncio.sleep(0.02)
    done = not state.streams and not state.pool.in_flight
    log.info(
        "drained %d stream(s) and %d solve(s) in flight%s",
        n_streams,
        n_jobs,
        "" if done else f"; gave up after {timeout:g} s",
    )
    return done


class InstanceHeader:
    """Every HTTP reply says which process answered (``X-Elastreg-Instance``)."""

    def __init__(self, app, instance_id: str) -> None:
        self.app = app
        self.header = (b"x-elastreg-instance", instance_id.encode())

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)

        async def send_with_header(message):
            if message["type"] == "http.response.start":
                message.setdefault("headers", [])
                message["headers"] = [*message["headers"], self.header]
            await send(message)

        return await self.app(scope, receive, send_with_header)


def create_app(settings: Settings | None = None) -> FastAPI:
    """The application over ``settings`` (default: :func:`get_settings`, from the environment)."""
    settings = settings or get_settings()
    closed = bool(settings.api_tokens)  # the docs pages cannot send a token: off on such a server
    app = FastAPI(
        title="elastreg",
        version=__version__,
        description="Real-time elastic registration of an organ's mesh to partial point clouds.",
        lifespan=lifespan,
        openapi_url=None if closed else "/openapi.json",
        docs_url=None if closed else "/docs",
        redoc_url=None if closed else "/redoc",
    )
    app.state.settings = settings

    async def own_settings() -> Settings:
        return settings

    app.dependency_overrides[deps.settings] = own_settings
    app.add_middleware(InstanceHeader, instance_id=settings.instance_id)
    if settings.allowed_origins:  # preflights of the listed origins (the guard refuses the rest)
        app.add_middleware(
            CORSMiddleware,
            allow_origins=list(settings.allowed_origins),
            allow_methods=["GET", "POST", "DELETE"],
            allow_headers=["authorization", "content-type", "accept"],
            expose_headers=["x-elastreg-instance", "retry-after"],
        )
    app.add_middleware(
        OriginGuard,
        allowed_origins=settings.allowed_origins,
        loopback_only=not settings.api_tokens and not settings.insecure,
    )
    app.add_middleware(KeepTransport)  # added last, so outermost: it sees the server's own send
    errors.install(app)
    authorized = [Depends(deps.owner)]
    app.include_router(health.router)  # the one endpoint without a token
    for module in (models, sessions):
        app.include_router(module.router, dependencies=authorized)
    # WebSocket routes authorize themselves (deps.authorize_websocket); the viewer's page is
    # public: its token stays in the URL's fragment, which browsers never send
    for module in (stream, watch, viewer):
        app.include_router(module.router)

    def openapi() -> dict:
        if app.openapi_schema is None:
            schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
            components = schema.setdefault("components", {}).setdefault("schemas", {})
            for model in REQUEST_MODELS:  # bodies the routes read themselves (JSON or MessagePack)
                js = model.model_json_schema(ref_template="#/components/schemas/{model}")
                components.update(js.pop("$defs", {}))
                components[model.__name__] = js
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi
    if closed:

        @app.get("/openapi.json", include_in_schema=False, dependencies=authorized)
        async def openapi_document():
            return JSONResponse(app.openapi())

    return app

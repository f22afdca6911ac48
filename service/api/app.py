"""The FastAPI application: ``create_app(settings)`` assembles middleware, handlers and routers;
its lifespan opens the model store and holds what requests share (app.state): the models, the
session registry with its sweeper, and the solve pool.

Run it with ``elastreg serve`` (:mod:`.server`), or ``uvicorn --factory service.api.app:create_app``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from .. import __version__
from ..config import Settings, get_settings, limit_threads
from . import deps, errors
from .routes import health, models, sessions, stream, viewer, watch
from .schemas import REQUEST_MODELS
from .sessions import SessionRegistry
from .work import SolvePool

log = logging.getLogger(__name__)

def _warm_up() -> None:
    """Compile (or load) the distance kernel now rather than in the first session."""
    import numpy as np

    from ..registration.distance import PointToSurface

    PointToSurface(np.array([[0, 1, 2]]))


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
    await asyncio.to_thread(_warm_up)
    log.info("instance %s: %d model(s) from %s (%d refused)",
             settings.instance_id, len(entries), settings.store, len(refused))
    app.state.models = entries
    app.state.store_errors = refused
    app.state.mesh_cache = {}
    app.state.registry = SessionRegistry(
        max_sessions=settings.max_sessions, ttl_s=settings.session_ttl_s, instance_id=settings.instance_id
    )
    app.state.pool = SolvePool(settings.solver_threads)
    sweeper = asyncio.create_task(_sweep(app.state.registry, settings.sweep_interval_s))
    try:
        yield
    finally:
        sweeper.cancel()
        app.state.pool.shutdown()


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
    app = FastAPI(
        title="elastreg",
        version=__version__,
        description="Real-time elastic registration of an organ's mesh to partial point clouds.",
        lifespan=lifespan,
    )
    app.state.settings = settings

    async def own_settings() -> Settings:
        return settings

    app.dependency_overrides[deps.settings] = own_settings
    app.add_middleware(InstanceHeader, instance_id=settings.instance_id)
    errors.install(app)
    for module in (health, models, sessions, stream, watch, viewer):
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
    return app

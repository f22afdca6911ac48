"""The models in the store: summaries, meshes, and the forward problem."""

from __future__ import annotations

from fastapi import APIRouter, Request

from .. import work
from ..deps import (
    ALT_MSGPACK,
    EntryDep,
    ModelsDep,
    PoolDep,
    ReplyKind,
    SettingsDep,
    SimulateBody,
    reply,
    request_body,
    unavailable,
)
from ..schemas.common import ErrorOut
from ..schemas.models import MeshOut, ModelSummary, SimulateIn, SimulateOut

router = APIRouter(prefix="/models", tags=["models"])
NOT_FOUND = {404: {"model": ErrorOut, "description": "unknown model"}}
BUSY = unavailable("at capacity, or shutting down: retry after Retry-After seconds (retry_after_s)")


@router.get("", response_model=list[ModelSummary], responses={200: {"content": ALT_MSGPACK}})
async def list_models(models: ModelsDep, kind: ReplyKind):
    return reply([work.summary(e) for e in models.values()], kind)


@router.get("/{model}", response_model=ModelSummary, responses={**NOT_FOUND, 200: {"content": ALT_MSGPACK}})
async def get_model(entry: EntryDep, kind: ReplyKind):
    return reply(work.summary(entry), kind)


@router.get("/{model}/mesh", response_model=MeshOut, responses={**NOT_FOUND, **BUSY, 200: {"content": ALT_MSGPACK}})
async def get_mesh(request: Request, entry: EntryDep, pool: PoolDep, kind: ReplyKind):
    encoded = await request.app.state.mesh_cache.get(  # once per model and encoding
        (entry.id, kind), lambda: pool.run(work.encode, work.mesh_payload(entry), kind)
    )
    return reply(encoded, kind)


@router.post(
    "/{model}/simulate",
    response_model=SimulateOut,
    responses={
        **NOT_FOUND,
        200: {"content": ALT_MSGPACK},
        422: {"model": ErrorOut},
        **BUSY,
    },
    openapi_extra=request_body(SimulateIn),
)
async def simulate(entry: EntryDep, body: SimulateBody, pool: PoolDep, settings: SettingsDep, kind: ReplyKind):
    work.check_E(body.value.E, entry, settings)
    data = await pool.run(
        work.simulate, entry, body.value, kind, {"decode": body.decode_ms}, body.t_received, settings.max_time_budget_ms
    )
    return reply(data, kind)

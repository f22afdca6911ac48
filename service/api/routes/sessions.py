"""Registration sessions over HTTP: open, post frames, inspect, close.

A session lives in the server process that opened it (docs/usage.md, "Scaling out", on session affinity).
"""

from __future__ import annotations

import logging

from fastapi import APIRouter, Request, Response

from .. import work
from ..deps import (
    ALT_MSGPACK,
    CreateBody,
    FrameBody,
    HttpSessionDep,
    ModelsDep,
    Owner,
    PoolDep,
    RegistryDep,
    ReplyKind,
    SettingsDep,
    client_gone,
    reply,
    request_body,
    unavailable,
)
from ..schemas.common import ErrorOut
from ..schemas.sessions import FrameIn, FrameResult, SessionCreate, SessionInfo, SessionOpened

log = logging.getLogger(__name__)
router = APIRouter(prefix="/sessions", tags=["sessions"])
NOT_FOUND = {
    404: {
        "model": ErrorOut,
        "description": "no such session in this process (see session affinity), or another token's",
    }
}
BUSY = unavailable(
    "at capacity (every solve thread busy and the queue full, or this session's frames queue full), or "
    "shutting down: retry after Retry-After seconds (retry_after_s)"
)
INVALID = {422: {"model": ErrorOut, "description": "a body that does not validate"}}


@router.post(
    "",
    status_code=201,
    response_model=SessionOpened,
    responses={
        201: {"content": ALT_MSGPACK},
        404: {"model": ErrorOut, "description": "unknown model"},
        **unavailable(
            "at the session limit (Retry-After: session_retry_after_s), or at capacity or shutting down "
            "(Retry-After: retry_after_s)"
        ),
        **INVALID,
    },
    openapi_extra=request_body(SessionCreate),
)
async def open_session(
    request: Request,
    body: CreateBody,
    models: ModelsDep,
    registry: RegistryDep,
    pool: PoolDep,
    settings: SettingsDep,
    kind: ReplyKind,
    owner: Owner,
):
    create = body.value
    entry = models.get(create.model)
    if entry is None:
        raise work.not_found_model(create.model, models)
    with client_gone(request) as gone:
        held = await work.open_session(
            entry, create, kind="http", registry=registry, pool=pool, settings=settings, owner=owner
        )
        if gone():  # nobody will learn its id: it would hold a slot until session_ttl_s
            registry.close(held.id, kind="http", owner=owner)
            log.info("session %s closed at once: its client left while it was being built", held.id)
    return reply(work.opened(held, settings.instance_id), kind, status=201)


@router.post(
    "/{session_id}/frames",
    response_model=FrameResult,
    responses={
        200: {"content": ALT_MSGPACK},
        **NOT_FOUND,
        **INVALID,
        **BUSY,
        413: {"model": ErrorOut, "description": "a point cloud over the limit"},
    },
    openapi_extra=request_body(FrameIn),
)
async def post_frame(
    request: Request,
    held: HttpSessionDep,
    body: FrameBody,
    registry: RegistryDep,
    pool: PoolDep,
    settings: SettingsDep,
    kind: ReplyKind,
):
    with client_gone(request) as gone:
        data = await work.http_frame(
            held,
            body.value,
            kind,
            decode_ms=body.decode_ms,
            t_received=body.t_received,
            registry=registry,
            pool=pool,
            session_queue=settings.session_queue,
            gone=gone,
        )
    return reply(data, kind)


@router.get("/{session_id}", response_model=SessionInfo, responses={200: {"content": ALT_MSGPACK}, **NOT_FOUND})
async def get_session(session_id: str, registry: RegistryDep, kind: ReplyKind, owner: Owner):
    return reply(work.info(registry.get(session_id, touch=False, owner=owner), registry), kind)


@router.delete("/{session_id}", status_code=204, response_class=Response, responses=NOT_FOUND)
async def close_session(session_id: str, registry: RegistryDep, owner: Owner):
    registry.close(session_id, kind="http", owner=owner)
    return Response(status_code=204)

"""``GET /health``: liveness, what is loaded, the limits, and which process answered."""

from __future__ import annotations

from fastapi import APIRouter, Request

from ... import __version__
from ..deps import ALT_MSGPACK, ModelsDep, RegistryDep, ReplyKind, SettingsDep, reply
from ..schemas import Health

router = APIRouter(tags=["health"])


@router.get("/health", response_model=Health, responses={200: {"content": ALT_MSGPACK}})
async def health(request: Request, settings: SettingsDep, models: ModelsDep, registry: RegistryDep, kind: ReplyKind):
    body = {
        "status": "ok",
        "models": len(models),
        "device": "cpu",
        "version": __version__,
        "limits": {
            "max_points": settings.max_points,
            "max_sessions": settings.max_sessions,
            "session_ttl_s": settings.session_ttl_s,
        },
        "instance": settings.instance_id,
        "sessions": registry.counts(),
        "solver_threads": settings.solver_threads,
        "skipped_models": request.app.state.store_errors,
    }
    return reply(body, kind)

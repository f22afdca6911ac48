"""``GET /health``: readiness, what is loaded, the limits, and which process answered. The one
endpoint without a token (load balancers and container health checks probe it).

``status`` is ``"degraded"`` with HTTP 503 when the process cannot serve registrations: no model
loaded, or every solve thread busy with a full queue behind it (the next frame would get a 503);
``reasons`` says which. A saturated one says when to ask again (``Retry-After``, as the frames'
503s); one without a model does not: that lasts until it restarts with a model.
"""

from __future__ import annotations

from fastapi import APIRouter, Request

from ... import __version__
from ..deps import ALT_MSGPACK, RETRY_AFTER, ModelsDep, PoolDep, RegistryDep, ReplyKind, SettingsDep, reply
from ..schemas.health import Health

router = APIRouter(tags=["health"])


@router.get(
    "/health",
    response_model=Health,
    responses={
        200: {"content": ALT_MSGPACK},
        503: {
            "model": Health,
            "description": "degraded: no model loaded, or the solve queue is full (then with Retry-After)",
            "headers": RETRY_AFTER,
        },
    },
)
async def health(
    request: Request, settings: SettingsDep, models: ModelsDep, registry: RegistryDep, pool: PoolDep, kind: ReplyKind
):
    reasons = []
    if not models:
        reasons.append(f"no model loaded from the store ({len(request.app.state.store_errors)} refused)")
    saturated = pool.saturated
    if saturated:
        reasons.append(f"the solve queue is saturated ({pool.in_flight} solves in flight)")
    body = {
        "status": "degraded" if reasons else "ok",
        "reasons": reasons,
        "models": len(models),
        "device": "cpu",
        "version": __version__,
        "limits": settings.limits,
        "instance": settings.instance_id,
        "sessions": {**registry.counts(), "closing": registry.closing},
        "solves": pool.counts(),
        "sockets": request.app.state.sockets,
        "tokenless_sockets": request.app.state.tokenless_sockets,
        "solver_threads": settings.solver_threads,
        "auth": "bearer" if settings.api_tokens else "none",
        "skipped_models": request.app.state.store_errors,
    }
    response = reply(body, kind, status=503 if reasons else 200)
    if saturated:
        response.headers["Retry-After"] = str(pool.retry_after)
    return response

"""``WS /stream``: a registration stream whose session lives with the connection."""

from __future__ import annotations

from fastapi import APIRouter, WebSocket

from ..streams import StreamRunner

router = APIRouter(tags=["stream"])


@router.websocket("/stream")
async def stream(websocket: WebSocket) -> None:
    """First message: a session config; then one frame per message, one result per frame."""
    await StreamRunner(websocket).run()

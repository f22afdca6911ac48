"""``GET /viewer``: the live viewer page and its scripts (shipped in the package), and the
synthetic sequence its demo mode streams (``GET /models/{model}/demo``).

The page loads nothing from outside this server: three.js is vendored (see
``service/api/viewer/vendor/README.md``). A token, when the server needs one, travels in the
URL's fragment (``#token=``), which browsers never send, so the page and its scripts are plain
static files; the page sends the token itself on every API call it makes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import FileResponse

from .. import deps
from ..deps import EntryDep, PoolDep, ReplyKind, reply
from ..errors import ApiError

router = APIRouter(tags=["viewer"])

HERE = Path(__file__).resolve().parents[1] / "viewer"
ASSETS = {  # an allow-list: no path from the URL ever reaches the filesystem
    "viewer.js": "text/javascript",
    "viewer.css": "text/css",
    "vendor/three.module.min.js": "text/javascript",
    "vendor/OrbitControls.js": "text/javascript",
    "vendor/LICENSE-three.txt": "text/plain",
}
DEMO_CACHE = 8  # sequences kept (oldest dropped first)
PEAK_FRACTION = 0.7  # of the model's training max_force, as in `elastreg demo`


@router.get("/viewer", include_in_schema=False)
async def viewer_page() -> FileResponse:
    return FileResponse(HERE / "index.html", media_type="text/html", headers={"cache-control": "no-cache"})


@router.get("/viewer/static/{name:path}", include_in_schema=False)
async def viewer_asset(name: str) -> FileResponse:
    media = ASSETS.get(name)
    if media is None:
        raise ApiError(404, f"no viewer file {name!r}")
    return FileResponse(HERE / name, media_type=media, headers={"cache-control": "max-age=3600"})


def demo_sequence(entry, frames: int, points: int, seed: int) -> dict:
    """A synthetic sequence over the model (:func:`service.synthetic.make_sequence`: a tool
    pulls a surface patch with a growing, turning force; the FEM gives each frame's shape)."""
    from ...synthetic import make_sequence, tool_patches

    mesh = entry.mesh
    tool, support = tool_patches(mesh, entry.region)
    max_force = float(entry.manifest.get("training", {}).get("load_distribution", {}).get("max_force", 1.0))
    seq = make_sequence(
        mesh,
        entry.fem.material,
        tool,
        n_frames=frames,
        peak_force=PEAK_FRACTION * max_force,
        n_points=points,
        noise=0.0,
        seed=seed,
    )
    if not seq.clouds:
        raise ApiError(422, "the FEM could not follow the first frame of the demo sequence")
    return {
        "model": entry.id,
        "tool": tool,
        "support": support,
        "clouds": np.stack([c.astype(np.float32) for c in seq.clouds]),
        "net_forces": seq.net_forces,
    }


# not in the OpenAPI document: a helper of the viewer's demo (docs/frontends.md), not the contract;
# a model endpoint, so it needs the token as they do (the page sends it from its fragment), and
# its FEM solves go through the solve pool (503 at capacity, not unbounded threads)
@router.get("/models/{model}/demo", tags=["viewer"], include_in_schema=False, dependencies=[Depends(deps.owner)])
async def demo(
    request: Request,
    entry: EntryDep,
    kind: ReplyKind,
    pool: PoolDep,
    frames: Annotated[int, Query(ge=2, le=120)] = 40,
    points: Annotated[int, Query(ge=10, le=5000)] = 500,
    seed: Annotated[int, Query(ge=0)] = 0,
):
    """A synthetic sequence for the viewer's demo: ``clouds`` (T, m, 3), the ``support`` to
    register over, the ``tool`` nodes that were pulled and the true ``net_forces`` (T, 3)."""
    if points > request.app.state.settings.max_points:
        raise ApiError(413, f"{points} points per cloud is over this server's limit")
    # one FEM solve per frame: made once per key, off the event loop
    sequence = await request.app.state.demo_sequences.get(
        (entry.id, frames, points, seed), lambda: pool.run(demo_sequence, entry, frames, points, seed)
    )
    return reply(sequence, kind)

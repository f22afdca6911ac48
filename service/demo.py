"""``elastreg demo``: serve a model, stream a synthetic sequence through the API, score it.

The server runs in this process (uvicorn on a free loopback port, in a background thread); the
demo is an ordinary client of it: it reads the model's mesh over HTTP, makes a sequence whose
answer is known (a tool pulls a patch of the surface with a growing, turning force; the FEM gives
the true shape of every frame; each frame's cloud samples the part a camera sees), and hands it
to the client side (:func:`clients.demo.score_stream`), which streams the clouds over the
WebSocket and prints, per frame, the registration error against the truth, the net-force error,
the client-side latency and the server's solve time, then a summary.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from clients.client import Client
from clients.demo import score_stream

from .config import Settings, default_store
from .fem.material import NeoHookean
from .mesh import TetMesh
from .synthetic import make_sequence

TOOL_NODES = 12
SUPPORT_NODES = 36
PEAK_FRACTION = 0.7  # of the model's training max_force


def patches(mesh, region: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A tool patch and a larger support around it, both free surface nodes in the region.

    The centre is the region's surface node nearest the region's surface centroid, so both
    patches grow inside the part of the surface the network was trained to load.
    """
    inside = np.zeros(mesh.n_nodes, bool)
    inside[region] = True
    cand = mesh.free_surface_nodes[inside[mesh.free_surface_nodes]]
    if cand.size == 0:
        raise ValueError("the model's load region has no free surface nodes")
    x = mesh.nodes[cand]
    centre = int(cand[np.argmin(np.linalg.norm(x - x.mean(axis=0), axis=1))])

    def patch(size: int) -> np.ndarray:
        p = mesh.surface_patch(centre, size)
        return np.sort(p[inside[p]])

    tool = mesh.surface_patch(centre, 3 * TOOL_NODES)  # nearest first: keep the closest in the region
    tool = tool[inside[tool]][:TOOL_NODES]
    return np.sort(tool), patch(SUPPORT_NODES)


def run(
    model: str = "phantom",
    frames: int = 20,
    method: str = "network",
    encoding: str = "msgpack",
    store=None,
    *,
    n_points: int = 1000,
    noise: float = 0.0005,
    seed: int = 0,
    out=None,
) -> int:
    """Run the demo; the exit code (0 when every frame came back)."""
    from .api.server import BackgroundServer  # uvicorn and FastAPI: only when a server runs

    out = out or sys.stdout

    def say(*args, **kw) -> None:
        print(*args, **kw, file=out, flush=True)

    store = Path(store) if store else default_store()
    build = f"elastreg train {model}" + (f" --store {store}" if store != default_store() else "")
    if not (store / model / "manifest.json").exists():
        say(f"error: no model {model!r} in the store at {store}.\nBuild it first with:  {build}")
        return 1

    say(f"starting the server over {store} ...", end=" ")
    t0 = time.perf_counter()
    with BackgroundServer(Settings(store=store)) as server, Client(server.url, encoding=encoding) as api:
        say(f"{server.url} ({time.perf_counter() - t0:.1f} s)")
        ids = [m["id"] for m in api.models()]
        if model not in ids:
            why = api.health()["skipped_models"].get(model, "not in the store")
            say(f"error: model {model!r} could not be loaded: {why}\nRebuild it with:  {build}")
            return 1
        summary = api.model(model)
        m = api.mesh(model)
        mesh = TetMesh(m["nodes"], m["tets"], m["fixed_nodes"])
        mat = summary["material"]
        material = NeoHookean(float(mat["E"]), float(mat["nu"]))
        tool, support = patches(mesh, m["region_nodes"])
        max_force = float(summary["training"].get("load_distribution", {}).get("max_force", 1.0))
        peak = PEAK_FRACTION * max_force
        say(f"model {model}: {mesh.n_nodes} nodes, {mesh.n_tets} tets; tool {tool.size} nodes, "
            f"support {support.size} nodes, peak force {peak:.3g} N; method {method}, {encoding}")
        say(f"making a synthetic sequence of {frames} frames (one FEM solve each) ...", end=" ")
        t0 = time.perf_counter()
        seq = make_sequence(mesh, material, tool, n_frames=frames, peak_force=peak, n_points=n_points,
                            noise=noise, seed=seed)
        say(f"{len(seq.clouds)} frames in {time.perf_counter() - t0:.1f} s")
        if not seq.clouds:
            say("error: the FEM could not follow the first frame of the sequence")
            return 1

        settings = None
        if method == "auto":  # correct frames past twice the build's validation error: the build's figure
            val = float(summary["training"].get("validation", {}).get("mean_mm", 0.5))
            settings = {"max_error": 2e-3 * val}
            say(f"auto: frames whose error estimate exceeds {2 * val:.3g} mm are registered again by the FEM")
        return score_stream(api, model, seq.clouds, seq.positions, seq.net_forces, mesh.nodes,
                            method=method, support=support, say=say, settings=settings)

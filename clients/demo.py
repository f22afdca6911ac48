"""``elastreg demo``: serve a model, stream a synthetic sequence through the API, score it.

The server runs in this process (uvicorn on a free loopback port, in a background thread); the
demo is an ordinary client of it: it reads the model's mesh over HTTP, makes a sequence whose
answer is known (a tool pulls a patch of the surface with a growing, turning force; the FEM gives
the true shape of every frame; each frame's cloud samples the part a camera sees), streams the
clouds over the WebSocket and prints, per frame, the registration error against the truth, the
net-force error, the client-side latency and the server's solve time, then a summary.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from .client import Client

TOOL_NODES = 12
SUPPORT_NODES = 36
PEAK_FRACTION = 0.7  # of the model's training max_force


def _patches(mesh, region: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A tool patch and a larger support around it (see :func:`service.synthetic.tool_patches`)."""
    from service.synthetic import tool_patches

    return tool_patches(mesh, region, TOOL_NODES, SUPPORT_NODES)


def _pct(a, q) -> float:
    return float(np.percentile(a, q)) if len(a) else float("nan")


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
    from service.api.server import BackgroundServer
    from service.config import Settings
    from service.fem.material import NeoHookean
    from service.mesh import TetMesh
    from service.store import default_store
    from service.synthetic import make_sequence

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
        tool, support = _patches(mesh, m["region_nodes"])
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

        say(f"{'frame':>5} {'error mm':>9} {'rest mm':>8} {'force %':>8} {'latency ms':>11} "
            f"{'solve ms':>9} {'iters':>6}  status")
        errors, rest_errors, force_errors, latency, solve = [], [], [], [], []
        failed = 0
        t_stream = time.perf_counter()
        with api.stream(model, method=method, support=support, outputs=["displacement", "forces"]) as stream:
            for t, cloud in enumerate(seq.clouds):
                t1 = time.perf_counter()
                r = stream.frame(cloud, frame_id=t)
                latency.append(1e3 * (time.perf_counter() - t1))
                truth = seq.positions[t]
                err = 1e3 * np.linalg.norm(mesh.nodes + r["displacement"] - truth, axis=1).mean()
                rest = 1e3 * np.linalg.norm(mesh.nodes - truth, axis=1).mean()
                f_true = seq.net_forces[t]
                f_err = 100 * np.linalg.norm(r["net_force"] - f_true) / max(np.linalg.norm(f_true), 1e-12)
                errors.append(err)
                rest_errors.append(rest)
                force_errors.append(f_err)
                solve.append(r["timing_ms"]["total"])
                failed += not r["converged"]
                say(f"{t + 1:>5} {err:>9.3f} {rest:>8.3f} {f_err:>8.1f} {latency[-1]:>11.1f} "
                    f"{solve[-1]:>9.1f} {r['iterations']:>6}  {r['status']}")
        seconds = time.perf_counter() - t_stream
    n = len(errors)
    say(f"\n{n} frames in {seconds:.2f} s ({n / seconds:.1f} frames/s); {n - failed} converged")
    say(f"registration error: median {np.median(errors):.3f} mm, p95 {_pct(errors, 95):.3f} mm "
        f"(undeformed shape: median {np.median(rest_errors):.3f} mm)")
    say(f"net force error:    median {np.median(force_errors):.1f} %, p95 {_pct(force_errors, 95):.1f} %")
    say(f"latency:            median {np.median(latency):.1f} ms, p95 {_pct(latency, 95):.1f} ms "
        f"(server solve: median {np.median(solve):.1f} ms, p95 {_pct(solve, 95):.1f} ms)")
    return 0


def viewer(model: str = "phantom", store=None, port: int | None = None, *, out=None) -> int:
    """``elastreg demo --viewer``: serve the model and open the viewer's demo (the page streams a
    synthetic sequence itself) until interrupted."""
    import webbrowser

    from service.api.server import BackgroundServer
    from service.config import Settings
    from service.store import default_store

    out = out or sys.stdout
    store = Path(store) if store else default_store()
    if not (store / model / "manifest.json").exists():
        print(f"error: no model {model!r} in the store at {store}.\nBuild it first with:  elastreg train {model}",
              file=out)
        return 1
    with BackgroundServer(Settings(store=store), port=port) as server:
        url = f"{server.url}/viewer?model={model}&demo=1"
        print(f"the viewer: {url}\n(watch any session with {server.url}/viewer?session=ID; Ctrl-C to stop)",
              file=out, flush=True)
        try:
            webbrowser.open(url)
        except Exception:  # no browser here: the URL above is enough
            pass
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            pass
    return 0

"""``elastreg demo``: serve a model, stream a synthetic sequence through the API, score it.

The server runs in this process (uvicorn on a loopback port, `--port` or a free one, in a
background thread, so a browser or client can watch the run there); the
demo is an ordinary client of it: it reads the model's mesh over HTTP, opens its session and
prints its id and the viewer's URL that watches it, makes a sequence whose
answer is known (a tool pulls a patch of the surface with a growing, turning force; the FEM gives
the true shape of every frame; each frame's cloud samples the part a camera sees), and hands it
to the client side (:func:`clients.demo.score_stream`), which streams the clouds over the
WebSocket and prints, per frame, the registration error against the truth, the net-force error,
the client-side latency and the server's solve time, then a summary.
"""

from __future__ import annotations

import shlex
import sys
import time
from pathlib import Path
from urllib.parse import quote

import numpy as np
from pydantic import ValidationError

from clients.client import Client, viewer_url
from clients.demo import OUTPUTS, score_stream

from .config import MAX_SESSION_TTL_S, Settings, default_store, setting_problems
from .fem.material import NeoHookean
from .mesh import TetMesh
from .synthetic import make_sequence, tool_patches

TOOL_NODES = 12
SUPPORT_NODES = 36
PEAK_FRACTION = 0.7  # of the model's training max_force
NOISE = 5e-4  # m per axis on every point of a cloud: a depth camera's, declared to the session


def session_settings(noise: float = NOISE) -> dict:
    """The demo's session: a camera knows its noise. Declared, it chooses alpha (the forces' MAP
    estimate, noise_prior) and the estimate carries it into the answer instead of counting it
    as misfit."""
    return {"noise": noise}


def patches(mesh, region: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The demo's tool patch and the support around it (:func:`service.synthetic.tool_patches`)."""
    return tool_patches(mesh, region, TOOL_NODES, SUPPORT_NODES)


def run(
    model: str = "phantom",
    frames: int = 20,
    method: str = "network",
    encoding: str = "msgpack",
    store=None,
    *,
    n_points: int = 1000,
    noise: float = NOISE,
    seed: int = 0,
    port: int | None = None,
    out=None,
    err=None,
) -> int:
    """Run the demo, its server on loopback `port` (None: a free one); the exit code (0 when
    every frame came back). Progress and scores go to `out` (stdout), errors to `err` (stderr)."""
    from .api.server import BackgroundServer  # uvicorn and FastAPI: only when a server runs

    out = out or sys.stdout

    def say(*args, **kw) -> None:
        print(*args, **kw, file=out, flush=True)

    def fail(text: str) -> int:
        print(text, file=err or sys.stderr, flush=True)
        return 1

    store = Path(store) if store else default_store()
    build = train_hint(model, store)
    # its own server: the session it opens before making the sequence (minutes on a big mesh)
    # must not expire as idle meanwhile, whatever ELASTREG_SESSION_TTL_S says
    own = _own_settings(model, store, port, build, session_ttl_s=MAX_SESSION_TTL_S)
    if isinstance(own, str):
        return fail(own)

    say(f"starting the server over {store} ...", end=" ")
    t0 = time.perf_counter()
    token = own.api_tokens[0] if own.api_tokens else None  # a server with tokens (ELASTREG_API_TOKENS) needs one
    with BackgroundServer(own, port=port) as server, Client(server.url, encoding=encoding, token=token) as api:
        say(f"{server.url} ({time.perf_counter() - t0:.1f} s)")
        ids = [m["id"] for m in api.models()]
        if model not in ids:
            why = api.health()["skipped_models"].get(model, "not in the store")
            return fail(f"error: model {model!r} could not be loaded: {why}\nRebuild it {build}")
        summary = api.model(model)
        m = api.mesh(model)
        mesh = TetMesh(m["nodes"], m["tets"], m["fixed_nodes"])
        mat = summary["material"]
        material = NeoHookean(float(mat["E"]), float(mat["nu"]))
        tool, support = patches(mesh, m["region_nodes"])
        max_force = float(summary["training"].get("load_distribution", {}).get("max_force", 1.0))
        peak = PEAK_FRACTION * max_force
        say(
            f"model {model}: {mesh.n_nodes} nodes, {mesh.n_tets} tets; tool {tool.size} nodes, "
            f"support {support.size} nodes, peak force {peak:.3g} N; method {method}, {encoding}"
        )
        settings = session_settings(noise)
        if method == "auto":  # correct frames past twice the build's validation error: the build's figure
            val = float(summary["training"].get("validation", {}).get("mean_mm", 0.5))
            settings["max_error"] = 2e-3 * val
        # the session opens before the sequence is made: a browser has those seconds to start watching it
        with api.stream(model, method=method, support=support, outputs=list(OUTPUTS), **settings) as stream:
            say(f"session {stream.session}: watch it at {viewer_url(server.url, stream.session)}")
            say(f"making a synthetic sequence of {frames} frames (one FEM solve each) ...", end=" ")
            t0 = time.perf_counter()
            seq = make_sequence(
                mesh, material, tool, n_frames=frames, peak_force=peak, n_points=n_points, noise=noise, seed=seed
            )
            say(f"{len(seq.clouds)} frames in {time.perf_counter() - t0:.1f} s")
            if not seq.clouds:
                return fail("error: the FEM could not follow the first frame of the sequence")
            say(f"the clouds' noise ({noise * 1e3:.3g} mm per axis) is declared; it chooses alpha, frame by frame")
            if method == "auto":
                say(f"auto: frames whose error estimate exceeds {2 * val:.3g} mm are registered again by the FEM")
            return score_stream(stream, seq.clouds, seq.positions, seq.net_forces, mesh.nodes, say=say)


def train_hint(model: str, store: Path) -> str:
    """How to build `model` into `store`, a command that works: a builtin scene's name builds
    itself; another id needs its scene file, which no name can stand for."""
    from .scene import BUILTIN_SCENES

    where = f" --store {shlex.quote(str(store))}" if store != default_store() else ""
    if model in BUILTIN_SCENES:
        return f"with:  elastreg train {model}{where}"
    return (
        f"from its scene file (no builtin scene is named {model!r}; builtins: {', '.join(BUILTIN_SCENES)}; "
        f"writing one: docs/scenes.md) with:  elastreg train SCENE.toml --name {model}{where}"
    )


def _own_settings(model: str, store: Path, port: int | None, build: str, **overrides) -> Settings | str:
    """The settings of a demo's own server over `store`, on loopback `port`; or, before anything
    starts, why it cannot run: no `model` in the store (`build` makes it), the port taken, or
    ELASTREG_* settings its server refuses (each setting and why, one line)."""
    if not (store / model / "manifest.json").exists():
        return f"error: no model {model!r} in the store at {store}.\nBuild it {build}"
    if port is not None and not _port_free(port):
        return _PORT_IN_USE.format(port=port)
    try:
        return Settings(store=store, **overrides)
    except ValidationError as exc:
        return f"error: the demo's server settings: {'; '.join(setting_problems(exc))}"


_PORT_IN_USE = "error: port {port} is in use (--port picks another, or leave it out for a free one)"


def _port_free(port: int) -> bool:
    """Whether a loopback port can be bound now, as the server binds it (the server's start-up
    would say so only in its log, and a failed lifespan reads the same there)."""
    from .api.server import listening_socket

    try:
        listening_socket("127.0.0.1", port).close()
    except SystemExit:  # its one-line refusal: the port is taken
        return False
    return True


def viewer(model: str = "phantom", store=None, port: int | None = None, *, out=None, err=None) -> int:
    """``elastreg demo --viewer``: serve the model and open the viewer's demo (the page streams a
    synthetic sequence itself) until interrupted: the server stops and the KeyboardInterrupt
    goes on to the caller (the command line's exit status 130). 1 when it cannot start, or the
    store refused the model."""
    import webbrowser

    from .api.server import BackgroundServer

    out = out or sys.stdout
    err = err or sys.stderr
    store = Path(store) if store else default_store()
    own = _own_settings(model, store, port, train_hint(model, store))
    if isinstance(own, str):
        print(own, file=err)
        return 1
    try:
        server = BackgroundServer(own, port=port).start()
    except RuntimeError as exc:
        print(f"error: the viewer's server could not start: {exc}", file=err)
        return 1
    try:
        if model not in server.app.state.models:  # refused by the store: the page could only fail
            why = server.app.state.store_errors.get(model, "not in the store")
            print(f"error: model {model!r} could not be loaded: {why}", file=err)
            return 1
        url = f"{server.url}/viewer?model={model}&demo=1"
        # a server with tokens: the page needs one, in the fragment (never sent to a server); the
        # browser opened here gets the first, the printed line only says where it goes
        fragment = f"#token={quote(own.api_tokens[0], safe='')}" if own.api_tokens else ""
        print(
            f"the viewer: {url}{'#token=TOKEN' if fragment else ''}\n"
            f"(watch any session with {server.url}/viewer?session=ID; Ctrl-C to stop)",
            file=out,
            flush=True,
        )
        try:
            webbrowser.open(url + fragment)
        except Exception:  # no browser here: the URL above is enough
            pass
        while True:  # until Ctrl-C: its KeyboardInterrupt goes up, after the server stopped
            time.sleep(3600)
    finally:
        server.stop()

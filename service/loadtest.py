"""``python -m service.loadtest``: frames for a served model, replayed by the client's load test.

    python -m service.loadtest --url http://127.0.0.1:8000 --model phantom --streams 4 --seconds 10

A server with tokens needs one: ``--token T``, or ``$ELASTREG_TOKEN``.

The frames need the model's geometry (a surface patch to pull, its normals, clouds sampled on
the deformed surface), so they are made here; the streams themselves are an ordinary client's
(:func:`clients.loadtest.run_load`).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys

import httpx
import numpy as np
from websockets.exceptions import WebSocketException

from clients.client import ApiError, AsyncClient, StreamError
from clients.loadtest import MAX_SECONDS, MAX_STREAMS, LoadReport, check_target, run_load

from .argtypes import whole_number
from .demo import PEAK_FRACTION, patches
from .mesh import TetMesh
from .registration.settings import METHODS
from .synthetic import sample_surface


async def make_frames(
    api: AsyncClient, model: str, *, n_frames: int = 8, n_points: int = 1000, seed: int = 0
) -> tuple[list[np.ndarray], np.ndarray]:
    """Clouds to replay, and the support to register them with: the network's displacement
    under a growing pull on a patch (``/simulate``), sampled on the deformed surface."""
    m = await api.mesh(model)
    summary = await api.model(model)
    mesh = TetMesh(m["nodes"], m["tets"], m["fixed_nodes"])
    tool, support = patches(mesh, m["region_nodes"])
    peak = PEAK_FRACTION * float(summary["training"].get("load_distribution", {}).get("max_force", 1.0))
    normal = mesh.patch_normal(tool)
    rng = np.random.default_rng(seed)
    clouds = []
    for t in range(n_frames):
        g = np.tile(normal * peak * (t + 1) / n_frames / tool.size, (tool.size, 1))
        u = (await api.simulate(model, tool, g, method="network"))["displacement"]
        pts, _, _ = sample_surface(mesh.nodes + u, mesh.surface_faces, n_points, rng)
        clouds.append(pts)
    return clouds, support


async def _run(args: argparse.Namespace) -> LoadReport:
    token = args.token or os.environ.get("ELASTREG_TOKEN")  # as `elastreg igtl --token` reads it
    async with AsyncClient(args.url, encoding=args.encoding, token=token) as api:
        frames, support = await make_frames(api, args.model, n_points=args.points)
    return await run_load(
        args.url,
        args.model,
        frames=frames,
        support=support,
        streams=args.streams,
        seconds=args.seconds,
        encoding=args.encoding,
        method=args.method,
        token=token,
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m service.loadtest", description=__doc__.split("\n\n")[0])
    p.add_argument("--url", default="http://127.0.0.1:8000", help="a loopback server (default %(default)s)")
    p.add_argument("--model", default="phantom")
    p.add_argument("--streams", type=int, default=4, help=f"concurrent streams (1..{MAX_STREAMS})")
    p.add_argument("--seconds", type=float, default=10.0, help=f"duration (at most {MAX_SECONDS:g})")
    p.add_argument("--encoding", choices=["msgpack", "json"], default="msgpack")
    p.add_argument("--method", choices=METHODS, default=METHODS[0])
    p.add_argument("--points", type=whole_number(1), default=1000, help="points per frame")
    p.add_argument("--token", default=None, help="the API token, for a server with tokens (default: $ELASTREG_TOKEN)")
    args = p.parse_args(argv)
    try:
        check_target(args.url, args.streams, args.seconds)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        report = asyncio.run(_run(args))
    except StreamError as exc:
        if exc.status == 0 and exc.close_code is not None:  # the server closed a stream (a frame
            # over its limits); websockets' exception, its cause, names the close code and its meaning
            print(f"error: the server at {args.url} closed a stream: {exc.__cause__ or exc.detail}", file=sys.stderr)
        else:  # the server refused a stream
            print(f"error: the server at {args.url} answered {exc}", file=sys.stderr)
        return 1
    except ApiError as exc:  # the server refused the model or the frames
        print(f"error: the server at {args.url} answered {exc}", file=sys.stderr)
        return 1
    except WebSocketException as exc:  # a socket that went wrong otherwise (not a server's)
        print(f"error: the server at {args.url} broke a stream: {exc}", file=sys.stderr)
        return 1
    except (httpx.ConnectError, OSError) as exc:
        print(f"error: cannot reach a server at {args.url} ({exc or type(exc).__name__})", file=sys.stderr)
        return 1
    except httpx.HTTPError as exc:  # reached, then a timeout or a broken reply
        print(f"error: a request to {args.url} failed ({type(exc).__name__}: {exc})", file=sys.stderr)
        return 1
    print(report.text())
    return 0 if report.errors == 0 else 1


if __name__ == "__main__":
    sys.exit(main())

"""``python -m service.loadtest``: frames for a served model, replayed by the client's load test.

    python -m service.loadtest --url http://127.0.0.1:8000 --model phantom --streams 4 --seconds 10

A server with tokens needs one: ``--token T``, or ``$ELASTREG_TOKEN``. ``--method auto`` needs
``--max-error M`` (metres: the estimate past which the FEM corrects a frame).

The figures go to stdout, also when the run ends early: Ctrl-C (then ``interrupted`` on stderr,
exit status 130), a stream the server closed, a server that stopped answering (one line on
stderr each, exit status 1; frozen before measuring began, it ends --seconds and REPLY_GRACE_S
after making the frames or opening the streams began). A run that measured no frame is a
failure (exit status 1); so is one with errors or unanswered frames. Frames refused at capacity
(503) are a figure of their own, not a failure: each stream waits the server's ``retry_after``
before its next try.

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
from clients.loadtest import MAX_SECONDS, MAX_STREAMS, REPLY_GRACE_S, LoadReport, Tally, check_target, run_load

from .argtypes import positive_number, whole_number
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


async def _run(args: argparse.Namespace, tally: Tally) -> LoadReport:
    token = args.token or os.environ.get("ELASTREG_TOKEN")  # as `elastreg igtl --token` reads it
    bound = args.seconds + REPLY_GRACE_S  # a server frozen before measuring ends the run in this too
    async with AsyncClient(args.url, encoding=args.encoding, token=token) as api:
        try:
            frames, support = await asyncio.wait_for(make_frames(api, args.model, n_points=args.points), bound)
        except TimeoutError:
            raise TimeoutError(f"the frames to replay were not made within {bound:g} s (--seconds and grace)") from None
    return await run_load(
        args.url,
        args.model,
        frames=frames,
        support=support,
        streams=args.streams,
        seconds=args.seconds,
        encoding=args.encoding,
        method=args.method,
        max_error=args.max_error,
        token=token,
        tally=tally,
    )


#: the line that says the streams are warm and the clock has started
_MEASURING = "measuring: {} stream(s) for {:g} s (Ctrl-C ends the run early, with its figures)"


def _closed(exc: StreamError) -> str:
    """Why a stream ended, truthfully: a close the server sent, or a connection this client
    found lost or gave up on (its keepalive ping unanswered: a server frozen or cut off)."""
    cause = exc.__cause__
    if getattr(cause, "rcvd", None) is not None:  # the server's close frame: its code and meaning
        return f"closed a stream: {cause}"
    sent = getattr(cause, "sent", None)
    if sent is not None and "keepalive ping timeout" in sent.reason:
        return "stopped answering: this client's keepalive ping went unanswered (the server frozen or cut off)"
    return f"lost a stream: {exc.detail}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m service.loadtest", description=__doc__.split("\n\n")[0])
    p.add_argument("--url", default="http://127.0.0.1:8000", help="a loopback server (default %(default)s)")
    p.add_argument("--model", default="phantom")
    p.add_argument("--streams", type=int, default=4, help=f"concurrent streams (1..{MAX_STREAMS})")
    p.add_argument(
        "--seconds",
        type=float,
        default=10.0,
        help=f"duration (at most {MAX_SECONDS:g}); frames in flight then get {REPLY_GRACE_S:g} s more",
    )
    p.add_argument("--encoding", choices=["msgpack", "json"], default="msgpack")
    p.add_argument("--method", choices=METHODS, default=METHODS[0])
    p.add_argument(
        "--max-error",
        type=positive_number(unit=" m"),
        default=None,
        help="method auto only (and needed there): the error estimate (metres) past which the FEM corrects a frame",
    )
    p.add_argument("--points", type=whole_number(1), default=1000, help="points per frame")
    p.add_argument("--token", default=None, help="the API token, for a server with tokens (default: $ELASTREG_TOKEN)")
    args = p.parse_args(argv)
    if args.method == "auto" and args.max_error is None:  # the server would refuse every stream
        p.error("--method auto needs --max-error (metres: the estimate past which the FEM corrects a frame)")
    if args.method != "auto" and args.max_error is not None:
        p.error("--max-error applies to --method auto only")
    try:
        check_target(args.url, args.streams, args.seconds)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    tally = Tally(on_start=lambda: print(_MEASURING.format(args.streams, args.seconds), file=sys.stderr, flush=True))
    try:
        report = asyncio.run(_run(args, tally))
    except KeyboardInterrupt:
        _measured(tally)
        print("interrupted", file=sys.stderr)
        return 130
    except StreamError as exc:
        if exc.status == 0 and exc.close_code is not None:  # a stream closed mid-run (a frame
            # over the server's limits, a restart, a frozen server)
            print(f"error: the server at {args.url} {_closed(exc)}", file=sys.stderr)
        else:  # the server refused a stream
            print(f"error: the server at {args.url} answered {exc}", file=sys.stderr)
        _measured(tally)
        return 1
    except ApiError as exc:  # the server refused the model or the frames
        print(f"error: the server at {args.url} answered {exc}", file=sys.stderr)
        return 1
    except WebSocketException as exc:  # a socket that went wrong otherwise (not a server's)
        print(f"error: the server at {args.url} broke a stream: {exc}", file=sys.stderr)
        _measured(tally)
        return 1
    except TimeoutError as exc:  # frozen before measuring began: making frames, or opening a stream
        print(f"error: the server at {args.url} stopped answering: {exc}", file=sys.stderr)
        return 1
    except (httpx.ConnectError, OSError) as exc:
        print(f"error: cannot reach a server at {args.url} ({exc or type(exc).__name__})", file=sys.stderr)
        return 1
    except httpx.HTTPError as exc:  # reached, then a timeout or a broken reply
        why = str(exc) or ("no reply in time" if isinstance(exc, httpx.TimeoutException) else "no detail given")
        print(f"error: a request to {args.url} failed ({type(exc).__name__}: {why})", file=sys.stderr)
        return 1
    print(report.text())
    if report.frames == 0:  # no figure to read: a failure, not a run
        print(f"error: no frame was answered in {args.seconds:g} s: nothing was measured", file=sys.stderr)
        return 1
    if report.unanswered:
        print(
            f"error: the server at {args.url} left {report.unanswered} frame(s) unanswered "
            f"{REPLY_GRACE_S:g} s past the run's end (frozen, or frames that slow)",
            file=sys.stderr,
        )
        return 1
    return 0 if report.errors == 0 else 1


def _measured(tally: Tally) -> None:
    """The figures of a run that ended early, where it had begun measuring."""
    if tally.started is not None:
        print(tally.report().text())


if __name__ == "__main__":
    sys.exit(main())

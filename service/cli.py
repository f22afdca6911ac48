"""elastreg: real-time elastic registration of organ meshes to partial point clouds.

Each subcommand parses its flags and calls one function."""

from __future__ import annotations

import argparse
import functools
import logging
import os
import shlex
import sys
from pathlib import Path

from .argtypes import build_minutes, model_id, positive, whole_number

_at_least_one = whole_number(1)
_at_least_zero = whole_number(0)
_port = whole_number(1, 65535)


def _seed(text: str) -> int:
    """A training seed, in the range TrainConfig takes (imported here: torch comes with it)."""
    from .surrogate.train import SEED_MAX

    return whole_number(0, SEED_MAX)(text)


def _device_name(text: str) -> str:
    """An argparse type for an OpenIGTLink device name: one a message's header can carry (any
    longer, and no cloud sent under it would ever be answered)."""
    from .igtl.protocol import check_device_name

    try:
        return check_device_name(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _train(args: argparse.Namespace) -> int:
    from .build import Interrupted, WorseThanInstalled, build
    from .scene import resolve_scene
    from .surrogate.cluster import ClusterError
    from .surrogate.data import done_indices
    from .surrogate.train import TrainConfig

    try:  # the config first: a bad combination of flags fails before the scene and any data
        config = TrainConfig(
            layout=args.layout,
            hidden=tuple(args.hidden),
            rank=args.rank,
            features=args.features,
            members=args.members,
            physics_skip=args.physics_skip,
            epochs=args.epochs,
            seed=args.seed,
        )
        scene = resolve_scene(args.scene)
    except ValueError as exc:  # a SceneError is one
        print(f"error: {exc}", file=sys.stderr)
        return 2
    command = "elastreg " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    try:
        report = _build_from(build, scene, config, command, args)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:  # Ctrl-C: one line, not the workers' tracebacks
        if isinstance(exc, Interrupted):
            kept = len(done_indices(exc.data_dir))
            print(f"interrupted: {kept} load paths kept in {exc.data_dir}; the same command resumes", file=sys.stderr)
        else:
            print("interrupted before any data", file=sys.stderr)
        return 130
    except WorseThanInstalled as exc:  # the store keeps the better model it has
        print(f"error: {exc}", file=sys.stderr)
        print(
            f"kept the installed {exc.entry_id}; rerun with --replace to install this build anyway "
            "(its data are kept for the rerun)",
            file=sys.stderr,
        )
        return 3
    except ClusterError as exc:  # a scheduler or workers that cannot be reached (it names which)
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # the disk: its message names the file
        print(f"error: {exc}", file=sys.stderr)
        return 2
    m = report.metrics
    print(
        f"{args.name or scene.name}: {report.samples} samples ({report.data_seconds:.0f} s of FEM), "
        f"trained in {report.train_seconds:.0f} s; validation mean {m['mean_mm']:.3f} mm, "
        f"p95 {m['p95_mm']:.3f} mm (u = 0: {m['zero_mean_mm']:.3f} mm"
        + (f"; linear alone: {m['linear_mean_mm']:.3f} mm" if "linear_mean_mm" in m else "")
        + f") -> {report.entry}"
    )
    return 0


def _build_from(build, scene, config, command: str, args: argparse.Namespace):
    from .config import default_store

    return build(
        scene,
        Path(args.store) if args.store else default_store(),
        samples=args.samples,
        workers=args.workers,
        scheduler=args.scheduler,
        data_root=Path(args.data) if args.data else None,
        config=config,
        command=command,
        name=args.name,
        minutes=args.minutes,
        replace=args.replace,
    )


def _serve(args: argparse.Namespace) -> int:
    from .api.server import serve

    serve(
        store=args.store,
        host=args.host,
        port=args.port,
        workers=args.workers,
        token_file=args.token_file,
        insecure=args.insecure,
        ssl_certfile=args.ssl_certfile,
        ssl_keyfile=args.ssl_keyfile,
    )
    return 0


def _demo(args: argparse.Namespace) -> int:
    from clients.client import ApiError, StreamError

    from .demo import run, viewer

    try:
        if args.viewer:
            return viewer(model=args.model, store=args.store, port=args.port)
        return run(
            model=args.model,
            frames=args.frames,
            method=args.method,
            encoding=args.encoding,
            store=args.store,
            port=args.port,
        )
    except KeyboardInterrupt:  # Ctrl-C, at any stage: the server stopped, one line, not a traceback
        print("interrupted", file=sys.stderr)
        return 130
    except ApiError as exc:  # the server refused a request or closed the stream: one line, not a traceback
        what = "stream" if isinstance(exc, StreamError) else "request"
        print(f"error: the demo's {what} failed: {' '.join(str(exc).split())}", file=sys.stderr)
        return 1


def _igtl(args: argparse.Namespace) -> int:
    from .igtl.bridge import run

    settings = {
        k: v
        for k, v in (
            ("method", args.method),
            ("alpha", args.alpha),
            ("gtol", args.gtol),
            ("max_iter", args.max_iter),
            ("force_bound", args.force_bound),
        )
        if v is not None
    }
    if args.support is not None:  # an empty --support is a file name too (none there), not "no support"
        from .scene import read_node_ids

        try:  # a scene's support_file's rules, several ids a line allowed
            settings["support"] = read_node_ids(Path(args.support), several_a_line=True).tolist()
        except ValueError as exc:  # a wrong command line, as ids the API refuses: one line, exit 2
            print(f"error: --support: {' '.join(str(exc).split())}", file=sys.stderr)
            return 2
    try:
        return run(
            args.model,
            host=args.host,
            port=args.port,
            server=args.server,
            store=args.store,
            device=args.device,
            settings=settings,
            token=args.token or os.environ.get("ELASTREG_TOKEN"),
            idle_timeout=args.idle_timeout,
        )
    except KeyboardInterrupt:  # Ctrl-C: clients told and closed, one line, as demo and train
        print("interrupted", file=sys.stderr)
        return 130


def _bench(args: argparse.Namespace) -> int:
    from .bench.report import main

    try:
        return main(args)
    except KeyboardInterrupt:  # Ctrl-C, in any part: the report as it was, one line, not a traceback
        print("interrupted", file=sys.stderr)
        return 130


def _command(sub, name: str, text: str) -> argparse.ArgumentParser:
    """A subcommand whose own --help says what it does, as the list of commands does."""
    return sub.add_parser(name, help=text, description=text)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="elastreg", description=__doc__)
    p.add_argument("-v", "--verbose", action="store_true", help="log progress (INFO)")
    sub = p.add_subparsers(dest="command", required=True)
    command = functools.partial(_command, sub)

    d = command(
        "demo",
        "serve the shipped default model, stream a synthetic sequence through the API, "
        "print error and latency per frame",
    )
    d.add_argument("--model", type=model_id, default="phantom", help="model id in the store (default: phantom)")
    d.add_argument("--frames", type=whole_number(2), default=20)
    d.add_argument(
        "--method",
        choices=["network", "fem", "auto"],
        default="network",
        help="auto: the network, with frames whose error estimate is large redone by the FEM",
    )
    d.add_argument("--encoding", choices=["msgpack", "json"], default="msgpack")
    d.add_argument("--store", default=None, help="model store (default: $ELASTREG_STORE or the project's model_store/)")
    d.add_argument(
        "--viewer", action="store_true", help="serve and open the live viewer's demo instead (Ctrl-C to stop)"
    )
    d.add_argument("--port", type=_port, default=None, help="the server's loopback port (default: a free one)")
    d.set_defaults(func=_demo)

    s = command("serve", "run the HTTP/WebSocket API over a model store")
    s.add_argument("--store", default=None, help="model store (default: $ELASTREG_STORE or the project's model_store/)")
    s.add_argument("--host", default="127.0.0.1")
    s.add_argument("--port", type=_port, default=8000)
    s.add_argument(
        "--workers",
        type=_at_least_one,
        default=1,
        help="server processes (sessions live in the process that made them)",
    )
    s.add_argument(
        "--token-file", default=None, help="bearer tokens, one a line (or ELASTREG_API_TOKENS); see docs/deployment.md"
    )
    s.add_argument("--insecure", action="store_true", help="serve a non-loopback address without tokens")
    s.add_argument("--ssl-certfile", default=None, help="TLS certificate (PEM): serve HTTPS and WSS")
    s.add_argument("--ssl-keyfile", default=None, help="the certificate's private key (PEM)")
    s.set_defaults(func=_serve)

    t = command("train", "generate FEM data for a scene and train its surrogate into the model store")
    t.add_argument("scene", help="a scene .toml, or a shipped scene name (beam, phantom)")
    t.add_argument("--store", default=None, help="model store (default: $ELASTREG_STORE or the project's model_store/)")
    t.add_argument(
        "--name", type=model_id, default=None, help="model id in the store (default: the scene's name; the same rule)"
    )
    t.add_argument("--samples", type=_at_least_one, default=None, help="samples to generate (default: the scene's)")
    t.add_argument(
        "--minutes",
        type=build_minutes,
        default=None,
        help="bound the whole build's wall time (at most a year): FEM data for 60 %% of it, training in the rest",
    )
    t.add_argument(
        "--workers",
        type=_at_least_zero,
        default=2,
        help="local Dask worker processes (one per core; 0: in this process)",
    )
    t.add_argument(
        "--replace",
        action="store_true",
        help="install the build even where it validates much worse than the model it replaces "
        "(without it the store keeps that one: exit status 3)",
    )
    t.add_argument("--scheduler", default=None, help="address of an existing Dask scheduler for the data generation")
    t.add_argument("--data", default=None, help="data folder root (default: $ELASTREG_DATA or ~/.cache/elastreg/data)")
    t.add_argument("--layout", choices=["reduced", "paper"], default="reduced")
    t.add_argument(
        "--hidden", type=_at_least_one, nargs="+", default=[512, 512], help="hidden layer widths (reduced layout)"
    )
    t.add_argument("--rank", type=_at_least_one, default=128, help="POD modes (reduced layout)")
    t.add_argument(
        "--members",
        type=_at_least_one,
        default=None,
        help="an ensemble of this many independently trained MLPs over one basis, averaged "
        "(reduced layout; default: the scene's [training] members, else 1)",
    )
    t.add_argument(
        "--physics-skip",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="the physics layout: the exact small-strain response outside the network, which "
        "reads its features and learns the remainder (default: on; --no-physics-skip trains on raw forces)",
    )
    t.add_argument(
        "--features", type=_at_least_one, default=256, help="linear-response POD modes the physics layout reads"
    )
    t.add_argument("--epochs", type=_at_least_one, default=200)
    t.add_argument("--seed", type=_seed, default=0)
    t.set_defaults(func=_train)

    g = command(
        "igtl",
        "an OpenIGTLink bridge (3D Slicer connects as a client): clouds in, "
        "the registered surface and a status out (docs/frontends.md)",
    )
    g.add_argument("--model", type=model_id, required=True, help="model id in the store")
    g.add_argument("--host", default="127.0.0.1")
    g.add_argument("--port", type=_port, default=18944, help="OpenIGTLink port (default: 18944)")
    g.add_argument("--server", default=None, help="URL of a running API (default: serve --store in this process)")
    g.add_argument(
        "--store",
        default=None,
        help="model store when no --server is given (default: $ELASTREG_STORE or the project's model_store/)",
    )
    g.add_argument(
        "--device",
        type=_device_name,
        default="cloud",
        help="device name of the incoming clouds, at most 20 ASCII characters (default: cloud)",
    )
    g.add_argument("--method", choices=["network", "fem"], default=None)
    g.add_argument("--alpha", type=float, default=None)
    g.add_argument("--gtol", type=float, default=None)
    g.add_argument("--max-iter", type=int, default=None)
    g.add_argument("--force-bound", type=float, default=None)
    g.add_argument(
        "--support",
        default=None,
        help="a file of node ids forces may act on: whitespace-separated ('#' comments), or a .npy array",
    )
    g.add_argument("--token", default=None, help="the API token, for a --server with tokens (default: $ELASTREG_TOKEN)")
    g.add_argument(
        "--idle-timeout",
        type=positive,
        default=None,
        metavar="SECONDS",
        help="a client silent this long gives the one slot up to a new connection (default: 10)",
    )
    g.set_defaults(func=_igtl)

    b = command("bench", "error against run time: tables and plots (see docs/usage.md)")
    from .bench.command import add_arguments

    add_arguments(b)
    b.set_defaults(func=_bench)
    return p


def _quiet_dask() -> None:
    """distributed's loggers at WARNING: its import sets them to INFO, and a build's ~30 lines of
    cluster start and stop would bury the scene's own warnings. Imported here (it is imported
    anyway for worker processes or a scheduler) so that the level set is the one that stays."""
    try:
        import distributed  # noqa: F401  (its import configures its loggers)
    except ImportError:
        return
    logging.getLogger("distributed").setLevel(logging.WARNING)


def _sync_cancel_race(record: logging.LogRecord) -> bool:
    """Drop distributed's own race on Ctrl-C: a KeyboardInterrupt that lands before its
    utils.sync has made its future schedules a cancel that reads the unset name, and tornado
    logs that NameError's traceback under our one-line "interrupted" (distributed 2026.8)."""
    exc = record.exc_info[1] if record.exc_info else None
    tb = exc.__traceback__ if isinstance(exc, NameError) else None
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    return not (
        tb is not None and tb.tb_frame.f_code.co_name == "cancel" and "distributed" in tb.tb_frame.f_code.co_filename
    )


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    # whatever the command and -v: train and bench run Dask, and the filter drops that race alone
    logging.getLogger("tornado.application").addFilter(_sync_cancel_race)
    builds_on_dask = (args.command == "train" and (args.workers or args.scheduler)) or (
        args.command == "bench" and "minutes" in args.parts  # its timed builds run a LocalCluster
    )
    if builds_on_dask and not args.verbose:
        _quiet_dask()
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())

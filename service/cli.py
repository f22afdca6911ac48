"""elastreg: real-time elastic registration of organ meshes to partial point clouds.

Each subcommand parses its flags and calls one function."""

from __future__ import annotations

import argparse
import functools
import logging
import os
import sys
import time

from . import commands
from .argtypes import (
    build_minutes,
    model_id,
    non_negative_number,
    positive,
    positive_number,
    scheduler_address,
    whole_number,
)
from .network_size import FEATURES, MAX_MEMBERS, MAX_WEIGHT_DECAY, MAX_WIDTH, WEIGHT_DECAY
from .started import process_started

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
    d.set_defaults(func=commands.demo)

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
    s.set_defaults(func=commands.serve)

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
    t.add_argument(
        "--scheduler",
        type=scheduler_address,
        default=None,
        help="address of an existing Dask scheduler for the data generation ([tcp://]HOST:PORT)",
    )
    t.add_argument("--data", default=None, help="data folder root (default: $ELASTREG_DATA or ~/.cache/elastreg/data)")
    t.add_argument("--layout", choices=["reduced", "paper"], default="reduced")
    t.add_argument(
        "--hidden",
        type=whole_number(1, MAX_WIDTH),
        nargs="+",
        default=[512, 512],
        help=f"hidden layer widths, each at most {MAX_WIDTH} (reduced layout)",
    )
    t.add_argument("--rank", type=_at_least_one, default=128, help="POD modes (reduced layout)")
    t.add_argument(
        "--members",
        type=whole_number(1, MAX_MEMBERS),
        default=None,
        help=f"an ensemble of this many (at most {MAX_MEMBERS}) independently trained MLPs over one basis, averaged "
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
        "--features", type=_at_least_one, default=FEATURES, help="linear-response POD modes the physics layout reads"
    )
    t.add_argument(
        "--weight-decay",
        type=non_negative_number(MAX_WEIGHT_DECAY),
        default=WEIGHT_DECAY,
        help=f"L2 weight decay of the weight matrices (default: {WEIGHT_DECAY:g}; 0: none)",
    )
    t.add_argument("--epochs", type=_at_least_one, default=200)
    t.add_argument("--seed", type=_seed, default=0)
    t.set_defaults(func=commands.train, actions=t._actions)  # actions: the manifest's rebuild command

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
    # the session settings' bounds (registration/settings.py), checked as the line is read
    g.add_argument("--alpha", type=positive, default=None, help="regularisation weight (> 0; default: the model's)")
    g.add_argument("--gtol", type=positive_number(1), default=None, help="relative gradient tolerance, in (0, 1]")
    g.add_argument("--max-iter", type=_at_least_one, default=None, help="iterations per frame (>= 1)")
    g.add_argument("--force-bound", type=positive, default=None, help="bound on each force component, N (> 0)")
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
        help=(
            "a client silent this long gives the one slot up to a new connection, and a new connection "
            "waits at most this long past the API's frame cap (its max_time_budget_ms) for the previous "
            "one's session to close (default: 10)"
        ),
    )
    g.set_defaults(func=commands.igtl)

    b = command("bench", "error against run time: tables and plots (see docs/usage.md)")
    from .bench.command import add_arguments

    add_arguments(b)
    b.set_defaults(func=commands.bench)
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
    entered = time.perf_counter()
    args = parser().parse_args(argv)
    if args.command in ("train", "bench"):  # the commands that train (bench's minutes part does)
        # before any thread exists that torch would compute on; the server keeps IEEE arithmetic,
        # where a client's 1e-310 stays a positive number
        from .config import flush_subnormals  # here: config's settings cost the other commands 0.1 s

        flush_subnormals()
    # --minutes counts from the command's start: the process's own where main is the process's
    # command (argv from sys.argv), else (a caller's argv: a test, a script) this call's
    args.started = process_started(entered) if argv is None else entered
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
    code = int(args.func(args) or 0)
    if argv is None and args.command == "train" and args.minutes is not None:
        _end_now(code)  # a timed command's wall time ends with its work
    return code


def _end_now(code: int) -> None:
    """End the process at once, its output flushed: the interpreter's teardown (torch's, numba's
    and MKL's modules and threads) took 1.7-3 s after a build's last line under a load of 13, past
    its --minutes. The entry is written and closed by then, and Dask's cluster closed."""
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    sys.exit(main())

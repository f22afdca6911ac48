"""What each `elastreg` subcommand runs (cli.py parses its flags): its work called with them,
and its failures as one line on stderr and an exit status, never a traceback."""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path


def train(args: argparse.Namespace) -> int:
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
            weight_decay=args.weight_decay,
            members=args.members,
            physics_skip=args.physics_skip,
            epochs=args.epochs,
            seed=args.seed,
        )
        scene = resolve_scene(args.scene)
    except ValueError as exc:  # a SceneError is one
        print(f"error: {exc}", file=sys.stderr)
        return 2
    command = rebuild_command(args)
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
    except (MemoryError, RuntimeError) as exc:  # torch's allocator says so with a RuntimeError
        if not out_of_memory(exc):
            raise
        said = " ".join(str(exc).split())[:200] or type(exc).__name__
        print(
            f"error: the build ran out of memory ({said}): "
            + (
                "train a smaller network (--hidden, --members, --rank, --features)"
                if trained(exc)
                else "the FEM data did (a smaller mesh, or fewer --workers, each holds one)"
            )
            + "; the data made are kept for the rerun",
            file=sys.stderr,
        )
        return 1
    m = report.metrics
    print(
        f"{args.name or scene.name}: {report.samples} samples ({report.data_seconds:.0f} s of FEM), "
        f"trained in {report.train_seconds:.0f} s; validation mean {m['mean_mm']:.3f} mm, "
        f"p95 {m['p95_mm']:.3f} mm (u = 0: {m['zero_mean_mm']:.3f} mm"
        + (f"; linear alone: {m['linear_mean_mm']:.3f} mm" if "linear_mean_mm" in m else "")
        + f") -> {report.entry}"
    )
    return 0


#: train's arguments that name a file or folder: recorded absolute, so the rebuild runs from anywhere
_PATHS = ("scene", "store", "data")
#: the flags that shape the network: recorded at any value, so a later default does not change a rebuild
_SHAPING = ("layout", "hidden", "rank", "physics_skip", "features", "weight_decay", "epochs", "seed")


def rebuild_command(args: argparse.Namespace) -> str:
    """The manifest's command that rebuilds the entry: the scene, the store it went to, the
    network's every setting and every other flag given a value other than its default; paths
    resolved (as typed, a relative one named another file, or none, from another folder; links
    resolved first, so `link/..` names what it did). A builtin scene's name stays a name."""
    from .config import default_store

    words = ["elastreg", "train"]
    for action in args.actions:  # train's, in the order --help lists them
        value = getattr(args, action.dest, None)
        if action.dest == "store":  # '' or none: the default store, itself maybe relative ($ELASTREG_STORE)
            value = value or str(default_store())
        elif action.dest == "help" or value in (None, "") or (value == action.default and action.dest not in _SHAPING):
            continue
        if action.dest in _PATHS and not (action.dest == "scene" and _builtin(value)):
            value = os.path.realpath(os.path.expanduser(value))
        if not action.option_strings:  # the scene, a positional
            words.append(value)
        elif isinstance(action, argparse.BooleanOptionalAction):
            words.append(action.option_strings[0 if value else 1])
        elif action.nargs == 0:  # --replace
            words.append(action.option_strings[0])
        else:
            words += [action.option_strings[0], *(map(str, value) if isinstance(value, list) else [str(value)])]
    return " ".join(shlex.quote(w) for w in words)


def _builtin(scene: str) -> bool:
    """Whether the scene argument names a builtin scene, as resolve_scene reads it."""
    from .scene import BUILTIN_SCENES

    path = Path(scene)
    return not (path.is_file() or path.suffix == ".toml") and scene in BUILTIN_SCENES


def out_of_memory(exc: BaseException) -> bool:
    """Whether `exc` is an allocation that failed: Python's MemoryError, or torch's (a
    RuntimeError on the CPU, its OutOfMemoryError subclass on a GPU)."""
    said = str(exc).lower()
    words = ("can't allocate memory", "cannot allocate memory", "not enough memory", "out of memory")
    return isinstance(exc, MemoryError) or any(w in said for w in words)


def trained(exc: BaseException) -> bool:
    """Whether an allocation failed in the training (torch, the network's code), not the FEM
    data: only there does a smaller network help."""
    import traceback

    files = [f.filename for f in traceback.extract_tb(exc.__traceback__)]
    return any(
        f"{os.sep}torch{os.sep}" in f or f.endswith(("surrogate/train.py", "surrogate/network.py")) for f in files
    )


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
        started=args.started,
    )


def serve(args: argparse.Namespace) -> int:
    from .api import server

    server.serve(
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


def demo(args: argparse.Namespace) -> int:
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


def igtl(args: argparse.Namespace) -> int:
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


def bench(args: argparse.Namespace) -> int:
    from .bench.report import main

    try:
        return main(args)
    except KeyboardInterrupt:  # Ctrl-C, in any part: the report as it was, one line, not a traceback
        print("interrupted", file=sys.stderr)
        return 130

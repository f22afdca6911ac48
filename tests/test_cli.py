"""The command line refuses impossible values at parse time, with the value named and exit
status 2, before any server starts or store loads."""

from __future__ import annotations

import json
import logging
import os
import re
import shlex
import shutil
import socket
import subprocess
import sys
from importlib import resources
from pathlib import Path

import pytest

from service.cli import main, parser
from service.scene import SceneError, parse_scene
from service.store import open_store
from tests.conftest import write_bar_scene


@pytest.mark.parametrize(
    "argv, words",
    [
        (["serve", "--port", "70000"], "whole number in 1..65535"),  # it bound 70000 - 65536 = 4464
        (["serve", "--port", "-1"], "whole number in 1..65535"),
        (["serve", "--workers", "0"], "whole number >= 1"),
        (["serve", "--workers", "-3"], "whole number >= 1"),
        (["igtl", "--model", "phantom", "--port", "0"], "whole number in 1..65535"),
        (["demo", "--frames", "0"], "whole number >= 2"),
        (["demo", "--viewer", "--port", "99999"], "whole number in 1..65535"),
        # a model id is the store's folder rule: a path would reach outside the store
        (["demo", "--model", "../other/phantom"], "argument --model: model id"),
        (["demo", "--viewer", "--model", ".."], "argument --model: model id"),
        (["igtl", "--model", "sub/phantom"], "argument --model: model id"),
        (["igtl", "--model", ""], "argument --model: model id"),
        # the session settings' bounds: taken as floats, nan and inf reached the API (or a solve)
        (["igtl", "--model", "phantom", "--alpha", "nan"], "--alpha: must be a positive finite number, got 'nan'"),
        (["igtl", "--model", "phantom", "--alpha", "0"], "--alpha: must be a positive finite number"),
        (["igtl", "--model", "phantom", "--gtol", "inf"], "--gtol: must be a positive finite number, got 'inf'"),
        (["igtl", "--model", "phantom", "--gtol", "2"], "--gtol: must be at most 1, got '2'"),
        (["igtl", "--model", "phantom", "--max-iter", "-5"], "--max-iter: must be a whole number >= 1, got '-5'"),
        (["igtl", "--model", "phantom", "--force-bound", "-1"], "--force-bound: must be a positive finite number"),
        # the network's size (service/network_size.py): past it, an allocation's traceback after the data
        (["train", "beam", "--hidden", "10000000", "10000000"], "--hidden: must be a whole number in 1..16384"),
        (["train", "beam", "--members", "100000"], "--members: must be a whole number in 1..64"),
    ],
)
def test_impossible_values_are_refused_at_parse_time(argv, words, capsys):
    with pytest.raises(SystemExit) as exit_:
        parser().parse_args(argv)
    assert exit_.value.code == 2 and words in capsys.readouterr().err


@pytest.mark.parametrize("minutes", ["1e308", "1e307", "525601"])
def test_a_build_budget_past_a_year_is_refused_at_parse_time(minutes, capsys):
    """60 * 1e308 minutes overflowed to an infinite deadline: a traceback after the scene loaded."""
    with pytest.raises(SystemExit) as exit_:
        parser().parse_args(["train", "beam", "--minutes", minutes])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and f"--minutes: must be at most 525600 (a year), got '{minutes}'" in err, err
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("elastreg train: error: argument")
    assert parser().parse_args(["train", "beam", "--minutes", "525600"]).minutes == 525600


def test_the_network_size_caps_are_taken_and_the_number_of_layers_bounded(tmp_path, capsys):
    args = parser().parse_args(["train", "beam", "--hidden", "16384", "16384", "--members", "64"])
    assert args.hidden == [16384, 16384] and args.members == 64
    assert main(["train", "beam", "--store", str(tmp_path / "s"), "--hidden", *["8"] * 65]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: hidden layers must be 1..64 widths in 1..16384") and "(65 layers)" in err, err
    assert not (tmp_path / "s").exists()


def test_good_values_parse():
    args = parser().parse_args(["serve", "--port", "8080", "--workers", "2"])
    assert (args.port, args.workers) == (8080, 2)
    assert parser().parse_args(["demo", "--frames", "2"]).frames == 2


NAMES = {  # a model id the scene and --name both take, or both refuse
    "liver": True,
    "liver.v2": True,  # the scene refused it, --name took it
    "liver_2-b.3": True,
    "L" * 64: True,
    "L" * 65: False,
    "..": False,  # a URL's parent segment
    ".": False,
    ".liver": False,  # hidden: the store skips it
    "..liver-1a2b3c4d": False,  # the name of an entry the store set aside (and restores)
    "-liver": False,
    "liver v2": False,
    "liver/v2": False,
    "liver%2f": False,
    "": False,
}


@pytest.mark.parametrize("name", NAMES)
def test_the_scene_name_and_the_name_flag_keep_one_rule(name, capsys):
    """A scene's `name` and `elastreg train --name` both give the model id in the store and in
    the API's URLs: they differed about '.', so a name one took the other refused."""
    text = resources.files("service.scene.shipped").joinpath("beam.toml").read_text()
    text = text.replace('name = "beam"', f"name = {json.dumps(name)}")
    try:
        parse_scene(text, "scene.toml")
        scene_takes = True
    except SceneError as exc:
        assert "name: must start with a letter or digit" in str(exc), exc
        scene_takes = False
    try:
        parser().parse_args(["train", "scene.toml", f"--name={name}"])
        flag_takes = True
    except SystemExit as exit_:
        assert exit_.code == 2 and "argument --name: model id" in capsys.readouterr().err
        flag_takes = False
    assert scene_takes == flag_takes == NAMES[name]


def test_a_model_id_with_a_dot_is_built_stored_and_served_by_it(tmp_path, bar):
    """From the scene's name through the store to the API's URL: /models/bar.v2 is that model."""
    import httpx

    from service.api.server import BackgroundServer
    from service.config import Settings

    scene = write_bar_scene(tmp_path / "scene", bar, name="bar.v2", samples=6)
    store = tmp_path / "store"
    rc = main(["train", str(scene), "--store", str(store), "--data", str(tmp_path / "data"), "--workers", "0",
               "--hidden", "16", "--rank", "4", "--features", "8", "--epochs", "2"])  # fmt: skip
    assert rc == 0
    entries, errors = open_store(store)
    assert sorted(entries) == ["bar.v2"] and not errors
    with BackgroundServer(Settings(store=store, blas_threads=0)) as server:
        r = httpx.get(f"{server.url}/models/bar.v2", timeout=30)
    assert r.status_code == 200 and r.json()["id"] == "bar.v2"


def _serve(store, *prefix: str) -> subprocess.CompletedProcess:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    argv = [*prefix, sys.executable, "-m", "service.cli", "serve", "--store", str(store), "--port", str(port)]
    return subprocess.run(argv, capture_output=True, text=True, timeout=60)  # a server that starts never ends


def test_serve_over_a_store_that_is_not_a_readable_folder_stops_at_once(tmp_path):
    """`elastreg serve --store` at a typo or a file started a server that could serve nothing
    (one warning in its log, /health degraded); an unreadable folder crashed its start-up with a
    traceback. Each is now one line and a non-zero exit, before uvicorn starts."""
    a_file = tmp_path / "store.txt"
    a_file.write_text("not a store")
    for store, words in ((tmp_path / "nowhere", "does not exist"), (a_file, "is not a folder")):
        r = _serve(store)
        assert r.returncode == 1, r.stderr
        assert r.stderr.strip() == f"error: model store {store} {words}; check --store or ELASTREG_STORE", r.stderr


@pytest.mark.skipif(os.name != "posix", reason="file modes")
def test_serve_over_an_unreadable_store_stops_at_once(tmp_path):
    store = tmp_path / "store"
    store.mkdir(mode=0)
    prefix: tuple[str, ...] = ()
    if os.geteuid() == 0:  # root lists any folder: drop the capabilities that let it
        if shutil.which("setpriv") is None:
            pytest.skip("root reads any folder, and setpriv (util-linux) is not here to drop that")
        prefix = ("setpriv", "--bounding-set", "-dac_override,-dac_read_search")
    r = _serve(store, *prefix)
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.strip().startswith(f"error: model store {store} cannot be read (Permission denied)"), r.stderr


def test_serve_on_a_port_in_use_stops_before_loading_any_model(tmp_path):
    """The port is taken before the models load and warm: a port in use was uvicorn's
    traceback-free but late refusal (exit 3), after seconds of start-up; now one line, exit 1."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        argv = [
            sys.executable,
            "-m",
            "service.cli",
            "serve",
            "--store",
            str(Path(__file__).parents[1] / "model_store"),
            "--port",
            str(port),
        ]
        r = subprocess.run(argv, capture_output=True, text=True, timeout=120)
    assert r.returncode == 1, r.stderr
    assert r.stderr.strip() == f"error: cannot listen on 127.0.0.1:{port} (Address already in use)", r.stderr
    assert "startup" not in r.stdout + r.stderr  # no application start-up: no model was loaded


def _demo(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """`elastreg demo` over the shipped store, 2 frames (`env`: ELASTREG_* settings added)."""
    store = str(Path(__file__).parents[1] / "model_store")
    argv = [sys.executable, "-m", "service.cli", "demo", "--store", store, "--frames", "2", *args]
    return subprocess.run(argv, capture_output=True, text=True, timeout=300, env={**os.environ, **(env or {})})


def test_distributeds_cancel_race_on_ctrl_c_is_not_logged_but_other_errors_are():
    """On Ctrl-C before distributed's utils.sync has made its future, its cancel callback raises
    NameError and tornado logged the traceback under our one-line "interrupted" (seen once in a
    fresh clone's run of test_ctrl_c_during_the_data_prints_one_line_and_keeps_the_paths)."""
    import logging

    from service.cli import _sync_cancel_race

    def record(source: str, filename: str) -> logging.LogRecord:
        namespace: dict = {}
        exec(compile(source, filename, "exec"), namespace)
        try:
            namespace["cancel"]()
        except Exception as exc:  # the exception as tornado's logger receives it
            info = (type(exc), exc, exc.__traceback__)
        return logging.LogRecord("tornado.application", logging.ERROR, filename, 1, "Exception in callback", None, info)

    race = "def cancel():\n    if future is not None:\n        future.cancel()\n    future = None\n"
    assert not _sync_cancel_race(record(race, "/venv/site-packages/distributed/utils.py"))
    assert _sync_cancel_race(record(race, "/work/service/other.py"))  # our own NameError: logged
    assert _sync_cancel_race(record("def cancel():\n    raise ValueError('x')\n", "/x/distributed/utils.py"))


# distributed's own race, as it happens: Ctrl-C while utils.sync's coroutine waits behind a busy
# loop, so its cancel callback reads a future not yet made; then another error in a callback
_RACE = r"""
import asyncio, os, signal, sys, threading, time
from distributed.utils import LoopRunner, sync
from service.cli import main

assert main(sys.argv[1:]) == 2  # refused (the store is a file) after the CLI set up its logging
runner = LoopRunner(asynchronous=False)
runner.start()
runner.loop.add_callback(time.sleep, 1.0)  # the loop busy: sync's coroutine has not made its future
threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGINT)).start()
try:
    sync(runner.loop, asyncio.sleep, 0.5)
    sys.exit("no Ctrl-C")
except KeyboardInterrupt:
    pass

def other():
    raise ValueError("another tornado error")

runner.loop.add_callback(other)
sync(runner.loop, asyncio.sleep, 1.0)  # queued behind the cancel and the other error: both ran
runner.stop()
"""


@pytest.mark.parametrize("verbose", [[], ["-v"]], ids=["quiet", "verbose"])
def test_a_build_with_dask_drops_distributeds_ctrl_c_race_with_or_without_v(tmp_path, bar, verbose):
    """`elastreg -v train --workers N` still printed distributed's NameError traceback on
    Ctrl-C: the filter was installed only where a build quietened Dask's logs (without -v)."""
    pytest.importorskip("distributed")
    scene = write_bar_scene(tmp_path / "scene", bar, samples=6)
    (tmp_path / "store").write_text("a file, not a folder")
    argv = [*verbose, "train", str(scene), "--store", str(tmp_path / "store"), "--data", str(tmp_path / "data"),
            "--workers", "1"]  # fmt: skip
    r = subprocess.run([sys.executable, "-c", _RACE, *argv], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "NameError" not in r.stderr, r.stderr[-3000:]
    assert "ValueError: another tornado error" in r.stderr, r.stderr[-3000:]  # any other error still shows


@pytest.mark.parametrize("verbose, level", [([], logging.WARNING), (["-v"], logging.INFO)], ids=["quiet", "verbose"])
def test_the_benchs_timed_builds_quiet_dasks_logs_unless_verbose(tmp_path, verbose, level):
    """`elastreg bench minutes` runs its timed builds on a LocalCluster, whose ~30 lines of start
    and stop buried the bench's own output: without -v distributed logs warnings only, as a
    build's do (a missing scene stops the bench once its logging is set)."""
    pytest.importorskip("distributed")
    log = logging.getLogger("distributed")
    before = log.level
    try:
        log.setLevel(logging.INFO)  # as distributed's import leaves it
        with pytest.raises(SystemExit) as exit_:  # refused: "cannot read the scene file", exit status 2
            main([*verbose, "bench", "minutes", "--scenes", str(tmp_path / "no.toml"), "--out", str(tmp_path / "out")])
        assert exit_.value.code == 2 and log.level == level
    finally:
        log.setLevel(before)


def test_a_port_whose_last_connection_waits_out_time_wait_is_free():
    """A server that closed its connection first leaves the port in TIME_WAIT for a minute;
    uvicorn binds it anyway (SO_REUSEADDR), so the demo's check must not call it in use (a
    second `elastreg demo --port P` straight after the first did)."""
    from service.demo import _port_free

    with socket.socket() as server:
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn's listener
        server.bind(("127.0.0.1", 0))
        server.listen()
        port = server.getsockname()[1]
        client = socket.create_connection(("127.0.0.1", port))
        conn, _ = server.accept()
        conn.close()  # the server's side closes first: its port goes to TIME_WAIT
        client.recv(1)
        client.close()
    assert _port_free(port)
    with socket.socket() as busy:  # a port something listens on is still refused
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        assert not _port_free(busy.getsockname()[1])


def test_the_demo_serves_on_the_port_asked_for():
    """`elastreg demo --port P` without --viewer: its server listens on P (a browser or client
    can watch the run there, at the viewer URL it prints with the session's id: it printed
    neither); it took a free port whatever P was. A port in use is one line and
    exit status 1 before anything starts, as with --viewer."""
    from service.api.server import free_port

    port = free_port()
    r = _demo("--port", str(port))
    assert r.returncode == 0, r.stderr
    assert f" ... http://127.0.0.1:{port} (" in r.stdout, r.stdout
    # once, before the sequence is made: the session's id and the page on P that watches it
    (sid,) = re.findall(rf"^session (\S+): watch it at http://127\.0\.0\.1:{port}/viewer\?session=\1$",
                        r.stdout, re.MULTILINE)  # fmt: skip
    assert r.stdout.index(f"session {sid}") < r.stdout.index("making a synthetic sequence"), r.stdout
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        r = _demo("--port", str(port))
    assert r.returncode == 1, r.stdout
    assert r.stderr.strip() == f"error: port {port} is in use (--port picks another, or leave it out for a free one)"
    assert "starting the server" not in r.stdout


def test_the_demos_session_outlives_a_ttl_shorter_than_its_sequence():
    """The demo opens its session before it makes the sequence (one FEM solve a frame): with
    ELASTREG_SESSION_TTL_S under that time its own server closed the stream as idle ("1000:
    idle") and the first frame raised a traceback. The demo's server keeps its session."""
    ttl = 0.05
    r = _demo(env={"ELASTREG_SESSION_TTL_S": str(ttl)})
    assert r.returncode == 0, r.stderr[-3000:]
    (made,) = re.findall(r"\.\.\. 2 frames in ([0-9.]+) s$", r.stdout, re.MULTILINE)
    assert float(made) > ttl, r.stdout  # the sequence did outlast the environment's TTL
    assert "2 frames in" in r.stdout and "2 converged" in r.stdout, r.stdout


def test_the_demo_runs_against_its_own_server_with_tokens():
    """With ELASTREG_API_TOKENS set, the demo's own server required a token its client never
    sent: the first request was a 401. Its client now sends one of the server's tokens."""
    r = _demo(env={"ELASTREG_API_TOKENS": "demo-token-aaaaaaaaaaaa,demo-token-bbbbbbbbbbbb"})
    assert r.returncode == 0, r.stderr[-3000:]
    assert "401" not in r.stderr and "frame" in r.stdout, r.stdout


def test_every_store_flag_says_it_defaults_to_elastreg_store(capsys):
    """demo and igtl read $ELASTREG_STORE before the project's store, as serve and train do, but
    their --help said only the project's model_store/."""
    for command in ("serve", "train", "demo", "igtl"):
        with pytest.raises(SystemExit):
            parser().parse_args([command, "--help"])
        flag = re.search(r"\n  --store STORE(.*?)(?=\n  -|\Z)", capsys.readouterr().out, re.S)
        assert flag and "$ELASTREG_STORE" in " ".join(flag[1].split()), (command, flag)


def test_settings_the_demos_server_refuses_end_it_in_one_line():
    """ELASTREG_* settings that contradict each other raised pydantic's traceback out of the
    demo: now one line naming the setting, and exit status 1."""
    r = _demo(env={"ELASTREG_MAX_MESSAGE_BYTES": "20000"})
    assert r.returncode == 1, r.stdout
    assert "Traceback" not in r.stderr, r.stderr[-3000:]
    (line,) = r.stderr.strip().splitlines()
    assert line.startswith("error: the demo's server settings: ") and "max_message_bytes" in line, line


def test_a_stream_error_ends_the_demo_in_one_line():
    """A server limit the demo's frames break (ELASTREG_MAX_POINTS under its 1000-point clouds,
    set for a real server in the same shell) raised the client's StreamError as a traceback:
    now one line and exit status 1."""
    r = _demo(env={"ELASTREG_MAX_POINTS": "500"})
    assert r.returncode == 1, r.stdout
    assert "Traceback" not in r.stderr, r.stderr[-3000:]
    assert r.stderr.splitlines()[-1] == (  # after the server's own log lines (its start's warning)
        "error: the demo's stream failed: 413: 1000 points is over this server's limit of 500 per frame"
    ), r.stderr[-3000:]


SEED_MAX = 2**64 - 1  # torch's manual_seed takes no larger one


@pytest.mark.parametrize("seed", ["-1", str(SEED_MAX + 1), "99999999999999999999", "1.5", "abc"])
def test_a_seed_the_trainer_cannot_take_is_refused_at_parse_time(seed, capsys):
    """`--seed -1` and `--seed 99999999999999999999` were taken and failed after all the FEM
    data, with numpy's or torch's words ("expected non-negative integer") naming no flag."""
    with pytest.raises(SystemExit) as exit_:
        parser().parse_args(["train", "beam", "--seed", seed])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and f"--seed: must be a whole number in 0..{SEED_MAX}, got {seed!r}" in err, err


def test_the_largest_seed_builds(tmp_path, bar):
    """The top of the range is one the whole build takes: the split, the POD bases and torch."""
    scene = write_bar_scene(tmp_path / "scene", bar, samples=6)
    rc = main(["train", str(scene), "--store", str(tmp_path / "store"), "--data", str(tmp_path / "data"),
               "--workers", "0", "--hidden", "16", "--rank", "4", "--features", "8", "--epochs", "2",
               "--seed", str(SEED_MAX)])  # fmt: skip
    assert rc == 0
    assert (
        json.loads((tmp_path / "store" / "bar" / "manifest.json").read_text())["training"]["config"]["seed"] == SEED_MAX
    )


def test_the_manifests_rebuild_command_names_its_paths_absolute(tmp_path, bar, monkeypatch):
    """Before: the rebuild command kept the paths as typed (relative to the folder it was typed
    in: from another, no scene file) and, when main was called with its own argv, the calling
    process's argv. Now it holds the scene, --store and --data absolute, and runs from anywhere."""
    write_bar_scene(tmp_path / "work" / "scenes", bar, samples=6)
    monkeypatch.chdir(tmp_path / "work")
    flags = ["--workers", "0", "--hidden", "16", "--rank", "4", "--features", "8", "--weight-decay", "3e-4",
             "--epochs", "2"]  # fmt: skip
    assert main(["train", "scenes/bar.toml", "--store", "store", "--data", "data", *flags]) == 0
    manifest = json.loads((tmp_path / "work" / "store" / "bar" / "manifest.json").read_text())
    rebuild = manifest["rebuild"]
    assert manifest["training"]["config"]["weight_decay"] == 3e-4
    work = (tmp_path / "work").resolve()  # the paths are recorded with links resolved
    assert rebuild == (
        f"elastreg train {work / 'scenes' / 'bar.toml'} --store {work / 'store'} --workers 0 --data {work / 'data'} "
        "--layout reduced --hidden 16 --rank 4 --physics-skip --features 8 --weight-decay 0.0003 --epochs 2 --seed 0"
    )  # the flags given and the network's every setting, in --help's order
    argv = shlex.split(rebuild)[1:] + ["--name", "again"]
    r = subprocess.run([sys.executable, "-m", "service.cli", *argv], capture_output=True, text=True, cwd=tmp_path,
                       timeout=300)  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    assert (work / "store" / "again" / "manifest.json").is_file()
    from service.commands import rebuild_command

    monkeypatch.setenv("ELASTREG_STORE", "relative-store")  # the default store, resolved where it was
    builtin = parser().parse_args(["train", "beam", "--no-physics-skip", "--replace", "--store", "", "--data", ""])
    assert rebuild_command(builtin) == (  # a name stays a name; '' is the default, not the folder
        f"elastreg train beam --store {work / 'relative-store'} --replace --layout reduced --hidden 512 512 "
        "--rank 128 --no-physics-skip --features 256 --weight-decay 0.0 --epochs 200 --seed 0"
    )
    (work / "real").mkdir()
    (work / "real" / "s.toml").write_text("")
    (work / "real" / "inner").mkdir()
    (work / "inner-link").symlink_to(work / "real" / "inner")
    given = parser().parse_args(["train", "inner-link/../s.toml", "--epochs", "200"])  # at its default: kept
    assert rebuild_command(given).startswith(f"elastreg train {work / 'real' / 's.toml'} --store ")


def test_out_of_memory_advice_names_the_part_of_the_build_that_ran_out():
    """An allocation that failed in the FEM data was told to train a smaller network."""
    from service.commands import trained

    def raised_in(filename: str) -> BaseException:
        try:
            exec(compile("raise MemoryError('Unable to allocate 1.40 MiB')", filename, "exec"), {})
        except MemoryError as exc:
            return exc
        raise AssertionError("nothing raised")

    assert trained(raised_in(os.path.join("x", "service", "surrogate", "train.py")))
    assert not trained(raised_in(os.path.join("x", "service", "surrogate", "data.py")))
    assert not trained(raised_in(os.path.join("x", "service", "fem", "newton.py")))


@pytest.mark.parametrize(
    "model, hint",
    [
        ("nope", "from its scene file (no builtin scene is named 'nope'; builtins: beam, phantom; writing one: "
                 "docs/scenes.md) with:  elastreg train SCENE.toml --name nope --store {store}"),
        ("beam", "with:  elastreg train beam --store {store}"),
    ],
)  # fmt: skip
def test_the_demo_of_a_model_not_in_the_store_suggests_a_command_that_builds_it(tmp_path, model, hint):
    """Before: `--model nope` suggested `elastreg train nope`, which no scene answers. Now a
    builtin scene's name is the command, and another id is told it needs its scene file."""
    r = subprocess.run([sys.executable, "-m", "service.cli", "demo", "--model", model, "--store", str(tmp_path)],
                       capture_output=True, text=True, timeout=120)  # fmt: skip
    assert r.returncode == 1, r.stderr
    assert r.stderr.splitlines() == [
        f"error: no model {model!r} in the store at {tmp_path}.",
        "Build it " + hint.format(store=tmp_path),
    ]


#: a command's process, then arithmetic on subnormal float32s on every thread torch computes on
_FLUSHED = """
import contextlib, sys, torch
from service.cli import main
with contextlib.suppress(SystemExit):
    main(sys.argv[1:])
torch.set_num_threads(2)
print((torch.full((4_000_000,), 1e-39) * 1.0).abs().max().item())
"""


@pytest.mark.parametrize(
    ("command", "flushed"),
    [(["train", "no-such-scene.toml"], True), (["igtl", "liver", "--support", "no-such-file.txt"], False)],
)
def test_a_training_command_flushes_subnormals_on_all_its_threads(command, flushed, tmp_path):
    """Subnormals slowed a liver's training epochs 10x (docs/performance.md): a command that
    trains flushes them before torch's threads exist, as each thread copies its creator's flag.
    The others keep IEEE arithmetic, where a client's 1e-310 is still positive."""
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    r = subprocess.run([sys.executable, "-c", _FLUSHED, *command], capture_output=True, text=True, timeout=120,
                       cwd=tmp_path, env=env)  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    assert float(r.stdout.split()[-1]) == (0.0 if flushed else pytest.approx(1e-39, rel=1e-3)), r.stdout

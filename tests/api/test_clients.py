"""The Python client (sync and async, HTTP and WebSocket, JSON and MessagePack), the demo and
the load test, against the real server."""

from __future__ import annotations

import asyncio
import io
import re
import socket
import threading

import numpy as np
import pytest

from clients import ApiError, AsyncClient, Client, StreamError
from clients.loadtest import check_target, run_load
from service.demo import run as demo
from service.loadtest import main as loadtest_main
from tests.conftest import interrupt

from .conftest import occupied, wait_for


@pytest.mark.parametrize("encoding", ["msgpack", "json"])
def test_sync_client(live, entry, support, clouds, encoding):
    with Client(live.url, encoding=encoding) as api:
        assert api.health()["instance"] == "alpha"
        assert [m["id"] for m in api.models()] == ["bar"] and api.model("bar")["n_nodes"] == 81
        mesh = api.mesh("bar")
        assert mesh["nodes"].dtype == np.float64 and mesh["tets"].shape == (entry.mesh.n_tets, 4)
        g = np.tile([0.0, 0.0, 5.0 / support.size], (support.size, 1))
        u = api.simulate("bar", support, g)["displacement"]
        np.testing.assert_allclose(u, entry.network.predict(g[None], support)[0], rtol=1e-12, atol=1e-15)
        with api.open_session("bar", support=support, outputs=["displacement", "forces"]) as s:
            assert s.id.startswith("alpha-") and isinstance(s.config["support"], np.ndarray)
            r = s.frame(clouds[0], frame_id=1)
            assert r["displacement"].shape == (81, 3) and r["forces"].shape == (support.size, 3)
            assert r["net_force"].shape == (3,) and r["frame_id"] == 1
            with pytest.raises(ApiError) as err:
                s.frame(np.zeros((3, 2)))
            assert err.value.status == 422
            with pytest.raises(ValueError, match="integer node ids"):  # not truncated to [1, 2]
                s.frame(clouds[0], support=[1.5, 2.0])
            assert s.info()["counters"]["frames"] == 1
        with api.stream("bar", support=support) as st:
            a = st.frame(clouds[0])
            with pytest.raises(StreamError) as err:
                st.frame(clouds[0], support=[0])
            assert err.value.status == 422 and "fixed" in err.value.detail and err.value.close_code is None
            st.send(clouds[1], frame_id="x")
            st.send(clouds[2], frame_id="y")
            assert [st.recv()["frame_id"], st.recv()["frame_id"]] == ["x", "y"]
            assert a["displacement"].shape == (81, 3)
        with pytest.raises(ApiError) as err:
            api.model("nope")
        assert err.value.status == 404 and err.value.instance == "alpha"
        with pytest.raises(StreamError) as err:
            api.stream("bar", alpha=-1.0)
        assert err.value.status == 422 and err.value.close_code == 1008


@pytest.mark.parametrize("encoding", ["msgpack", "json"])
def test_async_client(live, support, clouds, encoding):
    async def main():
        async with AsyncClient(live.url, encoding=encoding) as api:
            assert (await api.health())["status"] == "ok"
            assert (await api.mesh("bar"))["surface_faces"].shape[1] == 3
            s = await api.open_session("bar", support=support)
            r = await s.frame(clouds[0])
            assert r["displacement"].shape == (81, 3)
            await s.close()
            with pytest.raises(ApiError):
                await s.frame(clouds[0])
            streams = [await api.stream("bar", support=support) for _ in range(3)]
            results = await asyncio.gather(*(st.frame(clouds[i], frame_id=i) for i, st in enumerate(streams)))
            assert [r["frame_id"] for r in results] == [0, 1, 2]
            with pytest.raises(StreamError):
                await streams[0].frame(np.full((4, 3), 1.0), support=[-1])
            assert (await streams[0].frame(clouds[3]))["status"]
            for st in streams:
                await st.close()
            with pytest.raises(StreamError) as err:
                await api.stream("nope")
            assert err.value.status == 404 and err.value.close_code == 1008

    asyncio.run(main())


def test_async_streams_and_watches_open_in_async_with_as_the_sync_ones_do_in_with(live, support, clouds):
    """`async with api.stream(...)` was a TypeError (a coroutine is no async context manager):
    only `async with await api.stream(...)` worked. Both forms, and the plain await, now do."""

    async def main() -> None:
        async with AsyncClient(live.url) as api:
            async with api.stream("bar", support=support) as stream:
                assert (await stream.frame(clouds[0], frame_id="a"))["frame_id"] == "a"
                async with api.watch(stream.session) as frames:
                    await stream.frame(clouds[1], frame_id="b")
                    assert (await frames.recv(timeout=30))["result"]["frame_id"] == "b"
                assert frames.ws.close_code is not None  # closed by the block
            assert stream.ws.close_code is not None
            async with await api.stream("bar", support=support) as stream:
                assert (await stream.frame(clouds[2]))["displacement"].shape == (81, 3)
            assert stream.ws.close_code is not None
            stream = await api.stream("bar", support=support)
            assert (await stream.frame(clouds[3]))["status"]
            await stream.close()
            with pytest.raises(StreamError) as err:
                async with api.stream("nope"):
                    pass
            assert err.value.status == 404

    asyncio.run(main())


@pytest.mark.parametrize("encoding", ["msgpack", "json"])
def test_an_empty_support_is_the_servers_422_not_a_local_dtype_error(live, clouds, encoding):
    """[] is float64 to numpy: the client refused it as "dtype float64", not integer ids, where
    API.md has the server refuse an empty support with a 422 that says so."""
    with Client(live.url, encoding=encoding) as api:
        for empty in ([], np.array([], int), ()):
            with pytest.raises(ApiError) as err:
                api.open_session("bar", support=empty)
            assert err.value.status == 422 and "non-empty" in str(err.value.detail), err.value
        with pytest.raises(StreamError) as err:
            api.stream("bar", support=[])
        assert err.value.status == 422 and "non-empty" in str(err.value.detail), err.value
        with api.open_session("bar") as s, api.stream("bar") as st:
            for handle, refused in ((s, ApiError), (st, StreamError)):
                with pytest.raises(refused) as err:
                    handle.frame(clouds[0], support=[])
                assert err.value.status == 422 and "non-empty" in str(err.value.detail), err.value
            assert st.frame(clouds[0], frame_id="after")["frame_id"] == "after"  # the stream goes on


def test_a_watch_of_a_deleted_session_raises_stream_error(live, support, clouds):
    """A watch of a DELETEd session says so as a StreamError with its close code and reason (a
    stream the server closed: test_client_streams.py)."""
    from websockets.exceptions import ConnectionClosed

    with Client(live.url) as api, api.open_session("bar", support=support) as s, api.watch(s.id) as watch:
        s.frame(clouds[0])
        assert watch.recv()["seq"] == 1
        s.close()
        with pytest.raises(StreamError) as err:
            watch.recv()
        assert err.value.close_code == 1000 and isinstance(err.value.__cause__, ConnectionClosed)


def test_loadtest_bounds():
    check_target("http://127.0.0.1:8000", 4, 10)
    check_target("http://localhost:1", 1, 1)
    check_target("http://[::1]:8000", 64, 600)
    for url, n, s in [
        ("http://example.com", 1, 1),
        ("http://10.0.0.1:8000", 1, 1),
        ("ftp://127.0.0.1", 1, 1),
        ("http://127.0.0.1", 65, 1),
        ("http://127.0.0.1", 0, 1),
        ("http://127.0.0.1", 1, 601),
        ("http://127.0.0.1", 1, 0),
    ]:
        with pytest.raises(ValueError):
            check_target(url, n, s)
    assert loadtest_main(["--url", "http://192.168.1.1:8000", "--seconds", "1"]) == 2


def test_loadtest_errors_are_one_line_not_tracebacks(live, capsys):
    """A server that is not there, a model it does not serve, points it cannot take: one line on
    stderr and a failing exit status each (they were tracebacks)."""
    with socket.socket() as free:  # a loopback port nothing listens on
        free.bind(("127.0.0.1", 0))
        port = free.getsockname()[1]
    cases = [
        (["--url", f"http://127.0.0.1:{port}"], "cannot reach a server"),
        (["--url", live.url, "--model", "nosuch"], "404"),
        (["--url", live.url, "--model", "bar", "--points", "1000000"], "1009 (message too big)"),
    ]
    for argv, message in cases:
        assert loadtest_main([*argv, "--seconds", "1", "--streams", "1"]) == 1
        err = capsys.readouterr().err
        last = err.strip().splitlines()[-1]  # after a `measuring:` line where the streams got that far
        assert last.startswith("error: ") and message in last and "Traceback" not in err, err
    with pytest.raises(SystemExit) as exit_:
        loadtest_main(["--points", "-5"])
    assert exit_.value.code == 2 and "must be a whole number >= 1" in capsys.readouterr().err


def test_loadtest_takes_a_token_from_its_flag_or_the_environment(bar_store, monkeypatch, capsys):
    """The load test had no --token and read no $ELASTREG_TOKEN: against a server with tokens it
    could only fail with 401. With either it runs; without, the 401 is its one line."""
    from .conftest import start

    token = "load+test/token=0123456789"
    server = start(bar_store[0], instance_id="loaded", api_tokens=token)
    argv = ["--url", server.url, "--model", "bar", "--seconds", "1", "--streams", "1", "--points", "200"]
    try:
        monkeypatch.delenv("ELASTREG_TOKEN", raising=False)
        assert loadtest_main([*argv, "--token", token]) == 0, capsys.readouterr().err
        monkeypatch.setenv("ELASTREG_TOKEN", token)
        assert loadtest_main(argv) == 0, capsys.readouterr().err
        monkeypatch.delenv("ELASTREG_TOKEN")
        capsys.readouterr()
        assert loadtest_main(argv) == 1 and "401" in capsys.readouterr().err
    finally:
        server.stop()


def test_loadtest_runs(live, support, clouds):
    report = asyncio.run(run_load(live.url, "bar", streams=2, seconds=1.0, frames=clouds, support=support))
    assert report.frames > 0 and report.errors == 0 and len(report.per_stream) == 2
    d = report.as_dict()
    assert d["p50_ms"] <= d["p95_ms"] <= d["p99_ms"] and d["fps"] > 0
    assert "frames/s" in report.text()


def test_demo_on_the_bar(bar_store):
    out = io.StringIO()
    assert demo(model="bar", frames=3, store=bar_store[0], n_points=300, out=out) == 0
    text = out.getvalue()
    assert "latency" in text and "noise (0.5 mm per axis) is declared" in text
    # every frame converged, and the registered shape is nearer the truth than the rest shape
    frames, converged = map(int, re.search(r"(\d+) frames in .*; (\d+) converged", text).groups())
    assert frames == 3 and converged == 3, text
    error, rest = map(float, re.search(r"registration error: median ([\d.]+) mm.*median ([\d.]+) mm", text).groups())
    assert error < 0.5 * rest, text


class _WatchOnSessionLine(io.StringIO):
    """The demo's output, as a user at a browser reads it: on the line that names the session,
    watch it at the printed viewer URL's server (as the page does) and keep its frames."""

    def __init__(self) -> None:
        super().__init__()
        self.seqs: list[int] = []
        self.watcher: threading.Thread | None = None

    def write(self, text: str) -> int:
        said = re.search(r"session (\S+): watch it at (http://\S+)/viewer\?session=(\S+)", text)
        if said and self.watcher is None:
            assert said[1] == said[3], text
            client = Client(said[2])
            watch = client.watch(said[1])  # before the demo goes on: frame 1 is not sent yet

            def follow() -> None:
                with client, watch:
                    try:
                        while True:
                            self.seqs.append(watch.recv(timeout=120)["seq"])
                    except StreamError:  # the session ended (1000), or the server with it (1012)
                        pass

            self.watcher = threading.Thread(target=follow, daemon=True)
            self.watcher.start()
        return super().write(text)


def test_the_demo_names_its_session_and_a_browser_can_watch_it(bar_store):
    """`elastreg demo` never printed its session id, so a viewer opened on its port could not
    watch the run. The id and the viewer's URL come out before the sequence is made, while
    the session is open; watched from that line, every frame of the run arrives."""
    out = _WatchOnSessionLine()
    assert demo(model="bar", frames=3, store=bar_store[0], n_points=300, out=out) == 0
    text = out.getvalue()
    assert out.watcher is not None, text
    out.watcher.join(60)
    assert out.seqs == [1, 2, 3], text
    assert text.count("watch it at") == 1
    assert text.index("watch it at") < text.index("making a synthetic sequence"), text


def test_demo_without_the_model_names_the_command(bar_store):
    """On stderr, as the rest of the command line's errors (it went to stdout, where a run
    redirected to a file hid it)."""
    out, err = io.StringIO(), io.StringIO()
    assert demo(model="phantom", frames=3, store=bar_store[0], out=out, err=err) != 0
    assert err.getvalue().startswith("error: no model 'phantom'") and "elastreg train phantom" in err.getvalue()
    assert "error" not in out.getvalue()
    import subprocess
    import sys

    for flags in ([], ["--viewer"]):  # the command line, both modes
        r = subprocess.run(
            [sys.executable, "-m", "service.cli", "demo", *flags, "--store", str(bar_store[0]), "--model", "phantom"],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert r.returncode == 1 and r.stdout == "" and r.stderr.startswith("error: no model 'phantom'"), r


def test_a_frame_whose_reply_timed_out_puts_the_stream_out_of_step(live, support, clouds):
    """Its reply may still come, and would be taken for the next frame's: the next frame() says
    so instead of returning the previous frame's result (sync and async alike)."""

    def sync() -> None:
        with Client(live.url) as api, api.stream("bar", method="fem", support=support) as s:
            s.timeout = 1e-4  # no FEM frame answers this fast
            with pytest.raises(TimeoutError):
                s.frame(clouds[0], frame_id="a")
            with pytest.raises(StreamError, match="open a new stream"):
                s.frame(clouds[1], frame_id="b")

    async def asynchronous() -> None:
        async with AsyncClient(live.url) as api:
            s = await api.stream("bar", method="fem", support=support)
            s.timeout = 1e-4  # the async stream honours it too
            with pytest.raises(TimeoutError):
                await s.frame(clouds[0], frame_id="a")
            with pytest.raises(StreamError, match="open a new stream"):
                await s.frame(clouds[1], frame_id="b")
            await s.close()

    sync()
    asyncio.run(asynchronous())


def test_a_frame_cancelled_or_interrupted_before_its_reply_puts_the_stream_out_of_step(live, support, clouds):
    """A frame() left by a cancel (asyncio.wait_for, the usual bound) or by Ctrl-C while its
    reply was pending: the next frame() returned that late reply, the previous frame's result
    under the new frame's call. It raises the out-of-step StreamError now, as after a timeout.
    Each is left once the server has the frame: a fixed 0.3 s could end, on a loaded machine,
    before the frame was sent, and a frame never sent rightly leaves the stream in step."""
    import signal

    pool, registry = live.app.state.pool, live.app.state.registry

    def admitted(session: str) -> None:
        # its own session's busy count, not the pool's in_flight: a job left by an earlier test
        # (a timed-out FEM frame) that ends meanwhile hides this frame's +1 there
        assert wait_for(lambda: registry.get(session, touch=False).busy > 0, 30), "the frame never reached the server"

    async def cancelled() -> None:
        async with AsyncClient(live.url) as api:
            s = await api.stream("bar", support=support)
            with occupied(pool, pool.threads):  # the frame waits for a solver thread: no reply yet
                pending = asyncio.ensure_future(s.frame(clouds[0], frame_id="a"))
                await asyncio.to_thread(admitted, s.session)
                pending.cancel()
                with pytest.raises(asyncio.CancelledError):
                    await pending
            with pytest.raises(StreamError, match="open a new stream"):
                await s.frame(clouds[1], frame_id="b")
            await s.close()

    def interrupt(*_) -> None:
        raise KeyboardInterrupt

    asyncio.run(cancelled())
    previous = signal.signal(signal.SIGALRM, interrupt)
    main = threading.get_ident()
    try:
        with Client(live.url) as api, api.stream("bar", support=support) as s:
            with occupied(pool, pool.threads):
                ctrl_c = threading.Thread(  # Ctrl-C while the reply is pending
                    target=lambda: (admitted(s.session), signal.pthread_kill(main, signal.SIGALRM)), daemon=True
                )
                ctrl_c.start()
                with pytest.raises(KeyboardInterrupt):
                    s.frame(clouds[0], frame_id="a")
                ctrl_c.join(30)
            with pytest.raises(StreamError, match="open a new stream"):
                s.frame(clouds[1], frame_id="b")
    finally:
        signal.signal(signal.SIGALRM, previous)


def test_a_frame_refused_before_it_was_sent_leaves_the_stream_in_step(live, support, clouds):
    """Bad points raise before anything is sent; the stream's next frame is answered as usual."""
    with Client(live.url) as api, api.stream("bar", support=support) as s:
        with pytest.raises(ValueError, match="integer node ids"):
            s.frame(clouds[0], support=[1.5])
        assert s.frame(clouds[0], frame_id="c")["frame_id"] == "c"


def test_the_viewer_demo_on_a_busy_port_says_so(bar_store, capsys):
    """`elastreg demo --viewer --port P` with P taken: one line and exit status 1 (a traceback
    from the server's start-up before)."""
    from service.demo import viewer

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert viewer(model="bar", store=bar_store[0], port=port) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and f"port {port} is in use" in err and "Traceback" not in err


@pytest.mark.parametrize(
    "argv, after",
    [
        (["--frames", "2000"], "the clouds' noise"),  # streaming the sequence
        (["--viewer"], "Ctrl-C to stop"),  # the viewer's server, waiting for Ctrl-C
    ],
)
def test_ctrl_c_in_the_demo_is_one_line_and_exit_status_130(bar_store, argv, after):
    """Ctrl-C in `elastreg demo` was a traceback (exit by the signal), and in `--viewer` a silent
    exit 0; the rest of the command line answers it with one line and 130."""
    status, text = interrupt(["demo", "--store", str(bar_store[0]), "--model", "bar", *argv], after)
    assert status == 130 and "Traceback" not in text, text
    assert text.rstrip().splitlines()[-1] == "interrupted", text


def test_the_viewer_demo_of_a_model_the_store_refused_says_why(bar_store, tmp_path):
    """`elastreg demo --viewer --model M` where the store refuses M (a corrupt file) served and
    printed the page's URL anyway, for a page that could only show a 404, and ran until Ctrl-C;
    the streaming demo says why and exits 1, and so does the viewer now."""
    import os
    import shutil
    import subprocess
    import sys

    store = tmp_path / "store"
    shutil.copytree(bar_store[0] / "bar", store / "bar")
    (store / "bar" / "weights.safetensors").write_bytes(b"not the weights")
    r = subprocess.run(
        [sys.executable, "-m", "service.cli", "demo", "--viewer", "--store", str(store), "--model", "bar"],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "BROWSER": "true"},
    )
    assert r.returncode == 1 and "the viewer: " not in r.stdout, r.stdout + r.stderr
    assert "error: model 'bar' could not be loaded: bar: weights.safetensors does not match" in r.stderr, r.stderr


def test_a_stream_whose_server_died_says_its_connection_was_lost(bar_store, clouds):
    """A server killed outright sends no close frame (1006): the StreamError says the connection
    was lost, not that the server closed the stream."""
    import subprocess
    import sys
    import time

    import httpx

    from service.api.server import free_port

    port = free_port()
    argv = [sys.executable, "-m", "service.cli", "serve", "--store", str(bar_store[0]), "--port", str(port)]
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        url = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 120
        while True:
            try:
                with Client(url) as api:
                    api.health()
                break
            except (ApiError, OSError, httpx.TransportError):
                assert time.monotonic() < deadline and proc.poll() is None, "the server did not start"
                time.sleep(0.2)
        with Client(url) as api, api.stream("bar") as stream:
            stream.frame(clouds[0])
            proc.kill()
            proc.wait(30)
            with pytest.raises(StreamError) as err:
                stream.frame(clouds[1])
    finally:
        if proc.poll() is None:
            proc.kill()
    assert err.value.close_code == 1006 and "lost without a close frame" in err.value.detail, err.value


def test_the_viewer_demo_with_tokens_gives_its_browser_one_and_prints_none(bar_store, tmp_path):
    """With ELASTREG_API_TOKENS set, `elastreg demo --viewer` opened a page whose own requests
    its server refused (no token). The browser it opens now gets the first token in the URL's
    fragment (never sent to a server); the printed line says where a token goes, not which."""
    import os
    import signal
    import subprocess
    import sys
    import time

    opened = tmp_path / "opened"
    browser = tmp_path / "browser.sh"
    browser.write_text(f'#!/bin/sh\nprintf %s "$1" > {opened}\n')
    browser.chmod(0o755)
    token = "viewer+token/aaaaaaaaaa=="  # base64's + / =: percent-encoded in the fragment
    argv = [sys.executable, "-m", "service.cli", "demo", "--viewer", "--store", str(bar_store[0]), "--model", "bar"]
    env = {**os.environ, "BROWSER": str(browser), "ELASTREG_API_TOKENS": f"{token},viewer-token-bbbbbbbbbbbb"}
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        deadline = time.monotonic() + 120
        while not opened.exists() or not opened.read_text():
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr and proc.stderr.read()
            time.sleep(0.1)
        assert opened.read_text().endswith("/viewer?model=bar&demo=1#token=viewer%2Btoken%2Faaaaaaaaaa%3D%3D")
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    assert "/viewer?model=bar&demo=1#token=TOKEN" in out and token not in out + err, out + err


def test_the_viewer_demo_with_settings_its_server_refuses_says_so_in_one_line(bar_store):
    """ELASTREG_* settings that contradict each other raised pydantic's traceback: one line."""
    import os
    import subprocess
    import sys

    argv = [sys.executable, "-m", "service.cli", "demo", "--viewer", "--store", str(bar_store[0]), "--model", "bar"]
    env = {**os.environ, "BROWSER": "true", "ELASTREG_MAX_MESSAGE_BYTES": "20000"}
    r = subprocess.run(argv, capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
    (line,) = r.stderr.strip().splitlines()
    assert line.startswith("error: the demo's server settings: ") and "max_message_bytes" in line, line

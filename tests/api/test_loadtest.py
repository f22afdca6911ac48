"""The load test's ends and figures against real servers: past the server's capacity, Ctrl-C, a
stream the server closed, a frozen server, method auto, a run too short to measure."""

from __future__ import annotations

import asyncio
import math
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from clients.loadtest import REPLY_GRACE_S, run_load
from service.loadtest import main as loadtest_main

from .conftest import occupied, server_process, start

ROOT = Path(__file__).resolve().parents[2]


class LoadTest:
    """``python -m service.loadtest`` in a process of its own, as a terminal runs it (Ctrl-C is
    SIGINT's default): its stderr read as it comes, the time its ``measuring:`` line came kept."""

    def __init__(self, url: str, *flags: str) -> None:
        argv = [sys.executable, "-m", "service.loadtest", "--url", url, "--model", "bar", "--points", "200", *flags]
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                                     preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # fmt: skip
        self.err: list[str] = []
        self.measuring = threading.Event()
        self.measuring_at = math.nan
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.err.append(line)
            if line.startswith("measuring: "):
                self.measuring_at = time.monotonic()
                self.measuring.set()

    def measure_a_while(self) -> None:
        """Return a second after the clock started (the streams warm: frames are being measured)."""
        assert self.measuring.wait(120), "".join(self.err)
        time.sleep(1.0)

    def finish(self, timeout: float = 90) -> tuple[int, str, list[str], float]:
        """Its exit status, stdout, stderr lines and when it exited."""
        try:
            status = self.proc.wait(timeout)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
        ended = time.monotonic()
        assert self.proc.stdout is not None
        out = self.proc.stdout.read()
        self.reader.join(10)
        return status, out, [line.rstrip("\n") for line in self.err], ended


def figures(out: str, streams: int) -> str:
    """The one line of figures on stdout, with frames measured."""
    (line,) = out.strip().splitlines()
    assert line.startswith(f"{streams} stream(s), ") and not re.search(r" 0 frames", line), line
    return line


@pytest.fixture
def one_thread(bar_store):
    """A server of one solver thread and no queue: a second solve at once is refused (503)."""
    server = start(bar_store[0], instance_id="narrow", solver_threads=1, solve_queue=0)
    yield server
    server.stop()


@pytest.mark.parametrize("warmup", [0, 1])
def test_frames_refused_at_capacity_are_counted_and_retried_after_retry_after(one_thread, support, clouds, warmup):
    """Past the server's capacity, a 503 aborted the run in its warm-up (no figures), and without
    a warm-up was resent at once, thousands of times, as errors. Now each refusal is a figure of
    its own and its stream waits the server's retry_after (1 s) before its next try."""
    streams, seconds = 3, 2.5
    with occupied(one_thread.app.state.pool) as release:  # the only solver thread busy for 1.2 s
        threading.Timer(1.2, release.set).start()
        report = asyncio.run(
            run_load(
                one_thread.url, "bar", frames=clouds, support=support, streams=streams, seconds=seconds, warmup=warmup
            )
        )
    assert report.frames > 0 and report.errors == 0 and report.unanswered == 0, report.text()
    # one try per stream per retry_after at most, over the run (and the warm-up's refusals apart)
    assert report.refused <= streams * (seconds + 1), report.text()
    if not warmup:  # every stream's first frame met the busy thread
        assert report.refused >= streams, report.text()
    assert f"refused at capacity {report.refused}" in report.text()


def test_ctrl_c_prints_the_figures_so_far_in_one_line_and_exits_130(live):
    """Ctrl-C in a run printed a traceback and lost every figure measured."""
    run = LoadTest(live.url, "--streams", "2", "--seconds", "120")
    run.measure_a_while()
    run.proc.send_signal(signal.SIGINT)
    status, out, err, _ = run.finish()
    assert status == 130 and err[1:] == ["interrupted"] and err[0].startswith("measuring: 2 stream(s)"), err
    assert "errors 0" in figures(out, 2)


def test_a_stream_the_server_closed_mid_run_keeps_the_figures_measured(bar_store):
    """A server that shut down mid-run (1012) was one error line, every figure measured lost."""
    server = start(bar_store[0], instance_id="leaving")
    try:
        run = LoadTest(server.url, "--streams", "1", "--seconds", "60")
        run.measure_a_while()
    finally:
        server.stop()
    status, out, err, _ = run.finish()
    assert status == 1 and len(err) == 2 and "Traceback" not in "".join(err), err
    assert err[1].startswith(f"error: the server at {server.url} closed a stream: ") and "1012" in err[1], err
    figures(out, 1)


def test_a_frozen_server_ends_the_run_within_its_grace_and_says_so(bar_store):
    """A server stopped (SIGSTOP) mid-run: the run went ~48 s past its seconds, until the
    client's own keepalive ping timed out, and then blamed the server for closing the stream.
    Now it ends REPLY_GRACE_S past its seconds at most, with the figures and the frames left
    unanswered."""
    seconds = 3.0
    with server_process(bar_store[0]) as (server, url):
        run = LoadTest(url, "--streams", "2", "--seconds", str(seconds))
        run.measure_a_while()
        server.send_signal(signal.SIGSTOP)
        status, out, err, ended = run.finish()
    assert status == 1 and len(err) == 2 and "closed" not in err[1], err
    assert err[1] == f"error: the server at {url} left 2 frame(s) unanswered {REPLY_GRACE_S:g} s past the run's end " \
        "(frozen, or frames that slow)", err  # fmt: skip
    assert "unanswered 2" in figures(out, 2)
    took = ended - run.measuring_at
    assert took < seconds + REPLY_GRACE_S + 2, f"the run took {took:.1f} s"


def test_ctrl_c_against_a_frozen_server_exits_at_once_with_the_figures(bar_store):
    """Ctrl-C in a run whose server was frozen (SIGSTOP) took 10 s to exit: each stream's close
    waited websockets' close_timeout for a closing handshake the server would not answer. An
    interrupted run closes its streams the quick way, as one past its grace does."""
    with server_process(bar_store[0]) as (server, url):
        run = LoadTest(url, "--streams", "2", "--seconds", "120")
        run.measure_a_while()
        server.send_signal(signal.SIGSTOP)
        time.sleep(0.5)
        interrupted = time.monotonic()
        run.proc.send_signal(signal.SIGINT)
        status, out, err, ended = run.finish()
    assert status == 130 and err[1:] == ["interrupted"], err
    figures(out, 2)
    assert ended - interrupted < 3.0, f"it exited {ended - interrupted:.1f} s after Ctrl-C"


def test_a_server_frozen_before_measuring_ends_the_run_within_seconds_and_grace(bar_store, support, clouds):
    """A server frozen (SIGSTOP) before the clock started: making the frames waited httpx's 60 s
    and said "failed (ReadTimeout: )", no reason; opening a stream waited websockets' 60 s and
    more. Both are bounded by --seconds and REPLY_GRACE_S now, and say the server stopped
    answering."""
    seconds = 2.0
    with server_process(bar_store[0]) as (server, url):
        server.send_signal(signal.SIGSTOP)
        started = time.monotonic()
        run = LoadTest(url, "--streams", "2", "--seconds", str(seconds))
        status, out, err, ended = run.finish()
        assert status == 1 and out == "", (status, out, err)
        assert err == [f"error: the server at {url} stopped answering: the frames to replay were not made within "
                       f"{seconds + REPLY_GRACE_S:g} s (--seconds and grace)"], err  # fmt: skip
        # the process's own start (imports) apart, at most a second or two
        assert ended - started < seconds + REPLY_GRACE_S + 4, f"the run took {ended - started:.1f} s"

        started = time.monotonic()
        with pytest.raises(TimeoutError, match=f"no stream opened within {seconds + REPLY_GRACE_S:g} s"):
            asyncio.run(run_load(url, "bar", frames=clouds, support=support, streams=2, seconds=seconds))
        took = time.monotonic() - started
        assert took < seconds + REPLY_GRACE_S + 1, f"the run took {took:.1f} s"


def test_method_auto_takes_max_error_and_is_refused_without_it(live, capsys):
    """`--method auto` was a choice whose every stream the server refused (422: no max_error)."""
    argv = ["--url", live.url, "--model", "bar", "--streams", "1", "--seconds", "1", "--points", "200"]
    assert loadtest_main([*argv, "--method", "auto", "--max-error", "0.01"]) == 0, capsys.readouterr().err
    assert "errors 0" in capsys.readouterr().out
    for extra, words in [(["--method", "auto"], "--method auto needs --max-error"),
                         (["--max-error", "0.01"], "--max-error applies to --method auto only"),
                         (["--method", "auto", "--max-error", "-1"], "must be a positive finite number")]:  # fmt: skip
        with pytest.raises(SystemExit) as exit_:
            loadtest_main([*argv, *extra])
        assert exit_.value.code == 2 and words in capsys.readouterr().err


def test_a_run_that_measured_no_frame_is_a_failure(live, capsys):
    """`--seconds 1e-9` printed "0 frames ... p50 nan ms" and exited 0."""
    argv = ["--url", live.url, "--model", "bar", "--streams", "1", "--seconds", "1e-9", "--points", "200"]
    assert loadtest_main(argv) == 1
    out, err = capsys.readouterr()
    assert err.strip().splitlines()[-1] == "error: no frame was answered in 1e-09 s: nothing was measured", err
    assert not re.search(r"\bnan\b", out) and "no latency measured" in out, out

"""A frame's work on a spare core: beside the caller when a thread is free, inline when not."""

import threading

import pytest

from service import spare
from tests.conftest import spare_threads_busy


def test_a_job_runs_beside_the_caller_when_a_thread_is_free():
    started = threading.Event()

    def job():
        started.set()
        return threading.get_ident()

    beside = spare.Beside(job)
    assert started.wait(10.0)
    assert beside.result() != threading.get_ident()


def test_a_job_runs_inline_when_every_spare_thread_is_busy():
    """A loaded server's frame never waits in the queue: the caller takes its own job back."""
    with spare_threads_busy():
        beside = spare.Beside(threading.get_ident)
        assert beside.result() == threading.get_ident()


def test_a_failing_job_raises_in_the_caller():
    beside = spare.Beside(lambda: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        beside.result()


def test_no_core_is_spare_while_every_core_has_a_frame():
    """A loaded server runs every job inline: as many frames in progress as cores."""
    import contextlib
    import os

    with contextlib.ExitStack() as frames:
        for _ in range(os.cpu_count() or 1):
            frames.enter_context(spare.frame())
        assert not spare.spare()
        assert spare.Beside(threading.get_ident).result() == threading.get_ident()
    assert spare.spare()


def test_taken_is_the_result_if_begun_and_none_if_not():
    """`taken` lets a caller do a job its own way when no thread began it: the job then never runs."""
    ran: list[int] = []
    with spare_threads_busy():
        beside = spare.Beside(lambda: ran.append(1))
        assert beside.taken() is None
    assert not ran
    begun = threading.Event()
    beside = spare.Beside(lambda: begun.set() or 7)
    assert begun.wait(10.0) and beside.taken() == 7


def test_openmp_threads_idle_briefly_unless_told_otherwise():
    """Importing the service caps libgomp's spinning (it would take the spare core for ms after
    each two-thread factorisation), before torch loads it; a caller's own setting wins."""
    import os
    import subprocess
    import sys

    code = "import service, os; print(os.environ['GOMP_SPINCOUNT'])"
    env = {k: v for k, v in os.environ.items() if k != "GOMP_SPINCOUNT"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "10000"
    out = subprocess.run([sys.executable, "-c", code], env={**env, "GOMP_SPINCOUNT": "5"}, capture_output=True,
                         text=True, check=True)  # fmt: skip
    assert out.stdout.strip() == "5"


def test_only_a_frames_own_thread_may_take_the_spare_core():
    """helping(): inside a frame, on its thread, while fewer frames run than there are cores;
    never on the spare pool's threads (their jobs are the spare core's work already)."""
    import os

    assert not spare.helping()
    with spare.frame():
        assert spare.helping() == ((os.cpu_count() or 1) > 1)
        assert not spare._executor().submit(spare.helping).result()  # on the pool's thread itself
    assert not spare.helping()


def test_a_frame_takes_the_spare_core_only_while_the_pool_has_no_job():
    """helping(): a job handed beside (begun or waiting) keeps the frame's FEM on its own core,
    and once the job ended, or was taken back unbegun, the core is the frame's again."""
    import os

    if (os.cpu_count() or 1) < 2:
        pytest.skip("needs a core to spare")
    with spare.frame():
        assert spare.helping()
        release, begun = threading.Event(), threading.Event()
        job = spare.Beside(lambda: begun.set() or release.wait(10.0), start=True)
        assert begun.wait(10.0) and not spare.helping()
        release.set()
        assert job.result() and spare.helping()
        with spare_threads_busy():
            waiting = spare.Beside(lambda: 1, start=True)
            assert not spare.helping()
            assert waiting.taken() is None and spare.helping()  # cancelled: no longer counted
            waiting.drop()  # a second cancel counts nothing twice
            assert spare.helping()

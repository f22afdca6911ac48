"""The session registry (unit): limits, expiry on a fake clock, 404s that explain themselves,
and the settings' validators."""

from __future__ import annotations

import importlib.util
import os
import re
import site
import subprocess
import sys
from pathlib import Path

import pytest
from pydantic import ValidationError

from service.api.server import free_port
from service.api.sessions import Held, RegistryFull, SessionNotFound, SessionRegistry, WrongKind
from service.config import SOLVERS, Settings
from service.fem.linsolve import BACKENDS


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def held(reg: SessionRegistry, kind: str = "http") -> Held:
    r = reg.reserve(kind)
    return reg.commit(r, Held(id=r.id, kind=kind, model="m", session=None, config={}))


def test_limit_counts_reservations_and_frees_on_cancel():
    reg = SessionRegistry(max_sessions=2, ttl_s=10, instance_id="i1", retry_after=5)
    a = held(reg)
    r = reg.reserve("http")
    with pytest.raises(RegistryFull):
        reg.reserve("stream")
    reg.cancel(r)
    reg.cancel(r)  # twice is harmless
    held(reg, "stream")
    assert reg.counts() == {"open": 2, "http": 1, "stream": 1}
    reg.close(a.id)
    held(reg)


def test_one_owner_holds_at_most_its_share_and_every_way_out_frees_one():
    """A single token could take every slot and lock the others out for session_ttl_s. Each
    owner now holds at most max_per_owner; a slot comes back on cancel, close, expiry and, for a
    session closed mid-frame, when that frame ends."""
    clock = Clock()
    reg = SessionRegistry(max_sessions=8, ttl_s=10, instance_id="i1", retry_after=5, max_per_owner=3, clock=clock)

    def own(owner: str, kind: str = "http") -> Held:
        r = reg.reserve(kind, owner)
        return reg.commit(r, Held(id=r.id, kind=kind, model="m", session=None, config={}))

    a = [own("A"), own("A", "stream")]
    pending = reg.reserve("http", "A")
    with pytest.raises(RegistryFull, match=r"this token holds its maximum of 3 sessions .*max_sessions_per_token"):
        reg.reserve("http", "A")
    assert own("B").owner == "B" and a[0].owner == "A"  # another token is not locked out
    reg.cancel(pending)
    a.append(own("A"))
    reg.close(a[0].id)
    a.append(own("A"))
    reg.begin(a[1])  # closed mid-frame: the slot is A's until the frame ends
    reg.close(a[1].id)
    with pytest.raises(RegistryFull, match="this token"):
        reg.reserve("http", "A")
    reg.end(a[1])
    a.append(own("A"))
    clock.t = 11  # A's idle HTTP sessions expire: its three slots come back
    assert {h.id for h in a[2:]} <= set(reg.expire())
    for _ in range(3):
        own("A", "stream")
    with pytest.raises(RegistryFull, match="this token"):
        reg.reserve("stream", "A")


def test_idle_http_sessions_expire_streams_and_busy_ones_do_not():
    clock = Clock()
    reg = SessionRegistry(max_sessions=8, ttl_s=10, instance_id="i1", retry_after=5, clock=clock)
    idle, busy, stream = held(reg), held(reg), held(reg, "stream")
    reg.begin(busy)
    clock.t = 11
    assert reg.expire() == [idle.id]
    with pytest.raises(SessionNotFound, match="expired after 10 s"):
        reg.get(idle.id)
    reg.end(busy)
    clock.t = 15
    assert reg.expire() == []  # touched at 11 by end()
    clock.t = 22
    assert reg.expire() == [busy.id]
    assert reg.get(stream.id).kind == "stream"


def test_get_touches_unless_told_not_to():
    clock = Clock()
    reg = SessionRegistry(max_sessions=8, ttl_s=10, instance_id="i1", retry_after=5, clock=clock)
    h = held(reg)
    clock.t = 8
    reg.get(h.id, touch=False)
    assert reg.expires_in(h) == pytest.approx(2)
    reg.get(h.id)
    assert reg.expires_in(h) == pytest.approx(10)


def test_not_found_messages():
    reg = SessionRegistry(max_sessions=8, ttl_s=10, instance_id="i1", retry_after=5)
    with pytest.raises(SessionNotFound) as err:  # a restart or a mis-route: this process cannot tell
        reg.get("other-abc")
    message = str(err.value)
    assert "opened by another server process (instance 'other'; this server process is instance 'i1')" in message
    restart, misroute = message.index("this server restarted"), message.index("routed to more than one process")
    assert restart < misroute and "sessions do not survive a restart: open a new one" in message
    assert "affinity" in message[misroute:]
    with pytest.raises(SessionNotFound, match="never existed"):
        reg.get("i1-abc")
    h = held(reg)
    assert h.id.startswith(f"i1-{reg.boot}.") and len(reg.boot) == 6  # instance, this start, random part
    with pytest.raises(SessionNotFound, match="never existed"):  # this start's own id format, unknown here
        reg.get(f"i1-{reg.boot}.abc")
    earlier = SessionRegistry(max_sessions=8, ttl_s=10, instance_id="i1", retry_after=5)  # the same id, restarted
    with pytest.raises(SessionNotFound) as err:
        earlier.get(h.id)
    assert f"opened by an earlier start of this server (instance 'i1', start '{reg.boot}';" in str(err.value)
    reg.close(h.id)
    with pytest.raises(SessionNotFound, match="closed"):
        reg.get(h.id)
    s = held(reg, "stream")
    with pytest.raises(WrongKind):
        reg.get(s.id, kind="http")
    with pytest.raises(WrongKind):
        reg.close(s.id, kind="http")


def test_not_found_messages_point_at_the_scaling_out_section():
    """They said "see the README", which says nothing of session affinity."""
    reg = SessionRegistry(max_sessions=8, ttl_s=10, instance_id="i1", retry_after=5)
    usage = (Path(__file__).resolve().parents[2] / "docs" / "usage.md").read_text()
    for session_id in ("other-abc", "i1-abc"):
        with pytest.raises(SessionNotFound) as err:
            reg.get(session_id)
        message = str(err.value)
        section = re.search(r'session affinity: docs/usage\.md, "([^"]+)"', message)
        assert section and "README" not in message, message
        assert f"\n## {section[1]}\n" in usage and "affinity" in usage.partition(f"## {section[1]}")[2][:2000]


@pytest.mark.parametrize(
    "bad",
    [
        {"max_points": 0},
        {"max_sessions": 0},
        {"session_ttl_s": 0},
        {"solver_threads": 0},
        {"blas_threads": -1},
        {"blas_threads": 257},
        {"instance_id": "has-dash"},
        {"instance_id": ""},
        {"max_points": 1_000_000, "max_body_bytes": 1 << 20},
    ],
)
def test_settings_refuse_bad_values(bad, tmp_path):
    with pytest.raises(ValidationError):
        Settings(store=tmp_path, **bad)


def test_the_per_token_session_cap_is_half_the_sessions_with_tokens_and_none_without(tmp_path):
    token = "t" * 20
    tokens = f"{token},{'u' * 20}"
    assert Settings(store=tmp_path, max_sessions=64, api_tokens=tokens).max_sessions_per_token == 32
    assert Settings(store=tmp_path, max_sessions=1, api_tokens=tokens).max_sessions_per_token == 1
    # one token: one owner, whose deployment (a frontend, a load test) may use every slot
    assert Settings(store=tmp_path, max_sessions=64, api_tokens=token).max_sessions_per_token == 64
    assert (
        Settings(store=tmp_path, max_sessions=8, api_tokens=token, max_sessions_per_token=3).max_sessions_per_token == 3
    )
    # at most the process's cap; without tokens every client is one owner: the process's cap
    assert (
        Settings(store=tmp_path, max_sessions=8, api_tokens=token, max_sessions_per_token=20).max_sessions_per_token
        == 8
    )
    assert Settings(store=tmp_path, max_sessions=8).max_sessions_per_token == 8
    assert Settings(store=tmp_path, max_sessions=8, max_sessions_per_token=2).max_sessions_per_token == 8
    with pytest.raises(ValidationError):
        Settings(store=tmp_path, max_sessions_per_token=0)


def test_settings_from_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("ELASTREG_MAX_POINTS", "1234")
    monkeypatch.setenv("ELASTREG_STORE", str(tmp_path))
    monkeypatch.setenv("ELASTREG_SOLVER_THREADS", "3")
    s = Settings()
    assert (s.max_points, s.store, s.solver_threads) == (1234, tmp_path, 3)
    assert Settings().instance_id != s.instance_id  # a random id per process (per Settings)
    monkeypatch.setenv("ELASTREG_MAX_SESSIONS", "lots")
    with pytest.raises(ValidationError):
        Settings()


def test_settings_take_the_solvers_the_fem_has():
    assert set(SOLVERS) == set(BACKENDS)


@pytest.mark.parametrize(
    "solver, says",
    [
        ("bogus", "unknown solver 'bogus'; choose from pardiso, cholmod, superlu"),
        pytest.param(
            "cholmod",
            "pip install 'elastreg[cholmod]'",
            marks=pytest.mark.skipif(
                importlib.util.find_spec("sksparse") is not None, reason="scikit-sparse installed"
            ),
        ),
    ],
)
def test_serve_refuses_a_solver_it_cannot_use_in_one_line(solver, says, tmp_path):
    """Before: /health said ok, then POST /sessions was a 422 (bogus) or a 500 (cholmod)."""
    _refused_at_serve(sys.executable, solver, says, tmp_path)
    assert Settings(store=tmp_path, solver="superlu").solver == "superlu"
    assert Settings(store=tmp_path, solver="").solver is None


@pytest.fixture(scope="module")
def python_without_mkl(tmp_path_factory) -> str:
    """This environment less the mkl wheel, for real: a fresh venv that imports this one's
    packages (a .pth file) but has none of its prefix, where the wheel put mkl_rt. Its Python;
    run it without ELASTREG_MKL_RT and the user site, the probe's other places."""
    root = tmp_path_factory.mktemp("nomkl")
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(root / "venv")], check=True, timeout=120)
    python = str(root / "venv" / "bin" / "python")
    purelib = subprocess.run(
        [python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    ).stdout.strip()
    lines = [f"import site; site.addsitedir({p!r})\n" for p in site.getsitepackages()]
    Path(purelib, "elastreg_deps.pth").write_text("".join(lines))
    return python


def test_serve_refuses_pardiso_without_mkl_in_one_line(python_without_mkl, tmp_path, monkeypatch):
    """Before: only the name was checked, so a server without MKL started, then failed at its
    first session's PARDISO factorisation."""
    monkeypatch.delenv("ELASTREG_MKL_RT", raising=False)
    monkeypatch.setenv("PYTHONNOUSERSITE", "1")
    monkeypatch.setenv("PYTHONUSERBASE", str(tmp_path / "no-user-base"))
    probe = "from service.fem.linsolve import available_backends as a; print(*a())"
    backends = subprocess.run([python_without_mkl, "-c", probe], capture_output=True, text=True, timeout=120)
    assert backends.returncode == 0 and "pardiso" not in backends.stdout.split(), backends.stderr
    _refused_at_serve(python_without_mkl, "pardiso", "pip install mkl", tmp_path)


def _refused_at_serve(python: str, solver: str, says: str, tmp_path: Path) -> None:
    r = subprocess.run(
        [python, "-m", "service.cli", "serve", "--store", str(tmp_path), "--port", str(free_port())],
        capture_output=True,
        text=True,
        timeout=60,  # refused at once; the old code served on
        env={**os.environ, "ELASTREG_SOLVER": solver},
    )
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 1 and len(lines) == 1, r.stderr
    assert lines[0].startswith("error: ELASTREG_SOLVER: ") and says in lines[0]

"""Shared fixtures: small meshes built in code, so the default tests need nothing on disk."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from service import spare
from service.mesh import TetMesh
from service.phantoms import grid_tets

SHARED = Path(__file__).resolve().parents[2] / "shared"
LIVER = SHARED / "meshes" / "liver_paper"
#: CI sets CI=true and puts shared/ beside the checkout: there a missing ../shared is a failure
IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")


@contextlib.contextmanager
def spare_threads_busy() -> Iterator[None]:
    """Every thread of the spare pool held on a wait while the block runs: as on a server whose
    cores all run frames, a job handed to the pool is never begun."""
    release = threading.Event()
    pool = spare._executor()
    blockers = [pool.submit(release.wait, 60.0) for _ in range(pool._max_workers)]
    try:
        yield
    finally:
        release.set()
        for b in blockers:
            b.result()


def require_shared(path: Path) -> None:
    """Skip a test that needs ``path`` (under ../shared) when it is absent locally; in CI, fail."""
    if path.exists():
        return
    message = f"{path} is missing: the test needs ../shared beside the checkout"
    if IN_CI:
        pytest.fail(f"{message} (CI=true: the data must be there)", pytrace=False)
    pytest.skip(message)


@pytest.fixture
def liver_data() -> Path:
    """The paper's liver folder; skipped locally without it, a failure in CI."""
    require_shared(LIVER)
    return LIVER


@pytest.fixture(scope="session")
def bar() -> TetMesh:
    """A 4 x 1 x 1 bar of 8 x 2 x 2 hexes clamped at x = 0 (81 nodes)."""
    nodes, tets = grid_tets((8, 2, 2), 0.5)
    mesh, _ = TetMesh.build(nodes, tets, np.flatnonzero(nodes[:, 0] == 0.0))
    return mesh


@pytest.fixture(scope="session")
def cube() -> TetMesh:
    nodes, tets = grid_tets((2, 2, 2), 0.5)
    mesh, _ = TetMesh.build(nodes, tets, np.flatnonzero(nodes[:, 0] == 0.0))
    return mesh


def needs_liver():
    """Mark a test that reads ../shared/meshes/liver_paper (see ``liver_data``)."""
    return pytest.mark.usefixtures("liver_data")


BAR_SCENE = """
name = "{name}"

[mesh]
path = "bar.vtu"

[material]
law = "neo-hookean"
E = 4500.0
nu = 0.45

[boundary]
fixed_box = [[-0.01, -1, -1], [0.01, 2, 2]]

[training]
samples = {samples}
max_force = 60.0
patch_nodes = [3, 6]
load_steps = {load_steps}
"""


def write_bar_scene(folder: Path, bar: TetMesh, name: str = "bar", samples: int = 60, load_steps: int = 3) -> Path:
    """A scene TOML over the `bar` fixture's mesh: the smallest thing the trainer can build."""
    import meshio

    folder.mkdir(parents=True, exist_ok=True)
    meshio.write(folder / "bar.vtu", meshio.Mesh(bar.nodes, [("tetra", bar.tets)]))
    path = folder / f"{name}.toml"
    path.write_text(BAR_SCENE.format(name=name, samples=samples, load_steps=load_steps))
    return path


@pytest.fixture(scope="session")
def bar_store(tmp_path_factory, bar):
    """A model store with one small trained entry ("bar"), built by the real trainer."""
    from service.build import build
    from service.scene import load_scene
    from service.surrogate.train import TrainConfig

    root = tmp_path_factory.mktemp("bar_store")
    scene = load_scene(write_bar_scene(root / "scene", bar))
    # 54 training samples: the physics skip path (the small-strain response) is what makes so
    # little data usable (without it the force error of registration exceeds 100%)
    # its own settings throughout, the decay too: the session tests' figures (iterations, stalls) are this network's
    config = TrainConfig(hidden=(64, 64), rank=24, features=256, epochs=60, batch=32, lr=3e-3, weight_decay=0.0,
                         patience=60, physics_skip=True)  # fmt: skip
    report = build(
        scene,
        root / "store",
        workers=0,
        data_root=root / "data",
        config=config,
        command="elastreg train bar.toml",
        progress=False,
    )
    return root / "store", report


@pytest.fixture(scope="session")
def entry(bar_store):
    """The bar's trained entry, loaded in the test process."""
    from service.store import load_entry

    return load_entry(bar_store[0] / "bar")


#: a build's process writing its folder (the store's own start of write_entry), until killed
_WRITER = """
import sys
from pathlib import Path
from service.store import _build_folder
path, fd = _build_folder(Path(sys.argv[1]), "bar")
(path / "weights.safetensors").write_bytes(bytes(1 << 16))
print(path.name, flush=True)
sys.stdin.read()
"""


@contextlib.contextmanager
def build_writer(store: Path) -> Iterator[tuple[subprocess.Popen, str]]:
    """A real second process holding a build folder in `store` (yields the process and the
    folder's name); killed at the end if still alive."""
    p = subprocess.Popen([sys.executable, "-c", _WRITER, str(store)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                         text=True, cwd=Path(__file__).resolve().parents[1])  # fmt: skip
    try:
        yield p, p.stdout.readline().strip()
    finally:
        if p.poll() is None:
            p.kill()
        p.wait(timeout=30)


def interrupt(argv: list[str], after: str) -> tuple[int, str]:
    """Run `elastreg` in a process of its own, press Ctrl-C (SIGINT) once a line holding `after`
    is out, and return its exit status and everything it wrote."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "service.cli", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "BROWSER": "true", "PYTHONUNBUFFERED": "1"},  # no browser opens
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # as in a terminal
    )
    lines: list[str] = []
    seen = threading.Event()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line)
            if after in line:
                seen.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        assert seen.wait(180), "".join(lines)
        proc.send_signal(signal.SIGINT)
        status = proc.wait(90)
    finally:
        if proc.poll() is None:
            proc.kill()
    reader.join(10)
    return status, "".join(lines)


def correlated_paths(
    rng: np.random.Generator, paths: int, steps: int, ratio: float = 0.05, path_sd: float = 0.5, step_sd: float = 0.1
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Validation samples as a build holds them: `paths` load paths of `steps` steps of one
    growing load (sizes k * a_p), each path's errors one lognormal share of its sizes (the path's
    own effect, sd `path_sd` on the log scale) times a little per step. Returns each sample's
    error, size and path, and the true ratio E[error] / E[size] the validation estimates."""
    sizes = np.arange(1, steps + 1)[None] * rng.lognormal(0.0, 0.5, (paths, 1))
    share = np.exp(rng.normal(0.0, path_sd, (paths, 1)) + rng.normal(0.0, step_sd, (paths, steps)))
    truth = ratio * float(np.exp((path_sd**2 + step_sd**2) / 2))  # the lognormal's mean
    return (ratio * share * sizes).ravel(), sizes.ravel(), np.repeat(np.arange(paths), steps), truth


@contextlib.contextmanager
def small_disk(folder: Path, size: int) -> Iterator[Path]:
    """A tmpfs of `size` bytes mounted on `folder`: a disk that fills up, for real. Skips the
    test where mounting is not permitted (not root, a container without CAP_SYS_ADMIN)."""
    folder.mkdir(parents=True, exist_ok=True)
    if shutil.which("mount") is None:
        pytest.skip("no mount command")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)], capture_output=True,
                       text=True)  # fmt: skip
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], check=False)

"""Loading the store: every bad entry is skipped with a logged reason while the others load, and
the names in a manifest are checked before any file is read (a name like ``../../../dev/zero``
hung startup, hashing the endless device)."""

from __future__ import annotations

import errno
import json
import logging
import os
import re
import shutil
import signal
import stat
import time
from pathlib import Path

import numpy as np
import pytest

from service.store import UNLOCKED_BUILD_AGE_S, StoreError, load_entry, open_store, remove_stale_builds
from tests.conftest import build_writer, small_disk


def _edit(path, **changes):
    m = json.loads((path / "manifest.json").read_text())
    m.update(changes)
    for k, v in list(m.items()):
        if v is None:
            del m[k]
    (path / "manifest.json").write_text(json.dumps(m))


def _files(path, **names):
    m = json.loads((path / "manifest.json").read_text())
    m["files"] = names
    (path / "manifest.json").write_text(json.dumps(m))


DIGEST = "0" * 64
BAD = {
    "no_mesh_key": (lambda p: _edit(p, mesh=None), "no 'mesh'"),
    "no_network_key": (lambda p: _edit(p, network=None), "no 'network'"),
    "no_material_E": (lambda p: _edit(p, material={"nu": 0.45}), "E and nu"),
    "dev_zero": (lambda p: _files(p, **{"../../../dev/zero": DIGEST, "mesh.npz": DIGEST}), "must list"),
    "extra_file": (
        lambda p: _files(p, **{"mesh.npz": DIGEST, "weights.safetensors": DIGEST, "x": DIGEST}),
        "nothing else",
    ),
    "bad_digest": (lambda p: _files(p, **{"mesh.npz": "abc", "weights.safetensors": DIGEST}), "SHA-256"),
    "mesh_is_a_device": (lambda p: (p / "mesh.npz").unlink() or os.symlink("/dev/zero", p / "mesh.npz"), "outside"),
    "mesh_is_a_fifo": (lambda p: (p / "mesh.npz").unlink() or os.mkfifo(p / "mesh.npz"), "not a regular file"),
    "mesh_links_out": (lambda p: (p / "mesh.npz").unlink() or os.symlink("/etc/hostname", p / "mesh.npz"), "outside"),
    "bad_id": (lambda p: _edit(p, id="../x"), "id must match"),
    "a list": (lambda p: (p / "manifest.json").write_text("[1, 2]"), "folder name"),
    "not_an_object": (lambda p: (p / "manifest.json").write_text("[1, 2]"), "JSON object"),
    "bad_hidden": (lambda p: _edit(p, network={"layout": "reduced", "n_in": 3, "hidden": 5}), "network.hidden must be"),
    # wrong types and values in the manifest: its own reason, not "the weights do not fit" (a
    # string "64" was read as the widths [6, 4]) nor a TypeError's traceback
    "hidden_string": (lambda p: _network(p, hidden="64"), "network.hidden must be a list"),
    "hidden_null": (lambda p: _network(p, hidden=None), "network.hidden must be a list"),
    "n_in_string": (lambda p: _network(p, n_in="abc"), "network.n_in must be a whole number"),
    "members_zero": (lambda p: _network(p, members=0), "network.members must be"),
    "unknown_layout": (lambda p: _network(p, layout="transformer"), "layout 'transformer' is not"),
    "negative_E": (lambda p: _edit(p, material={"law": "neo-hookean", "E": -1.0, "nu": 0.3}), "material: Young's"),
    "nu_half": (lambda p: _edit(p, material={"law": "neo-hookean", "E": 1e4, "nu": 0.5}), "material: Poisson's"),
    # within what the law once took (E > 0, nu < 0.5), outside what a scene takes
    "E_over_range": (
        lambda p: _edit(p, material={"law": "neo-hookean", "E": 1e13, "nu": 0.45}),
        "material: Young's modulus E must be within [1, 1e+12] Pa, got 10000000000000.0",
    ),
    "nu_over_range": (
        lambda p: _edit(p, material={"law": "neo-hookean", "E": 4500.0, "nu": 0.4999999}),
        "material: Poisson's ratio nu must be within [0, 0.49999], got 0.4999999",
    ),
    "another_law": (lambda p: _edit(p, material={"law": "mooney-rivlin", "E": 1e4, "nu": 0.3}), "law 'mooney-rivlin'"),
    "renumbered_string": (lambda p: _mesh(p, renumbered="no"), "mesh.renumbered must be true or false"),
    "other_widths": (lambda p: _network(p, hidden=[32, 32]), "the weights do not fit the manifest"),
    # what the manifest records twice: an edited material.E was served at 10x what the network learnt
    "E_changed": (
        lambda p: _edit(p, material={"law": "neo-hookean", "E": 45000.0, "nu": 0.45}),
        "material.E 45000.0 is not the 4500.0 of the scene it was built from (scene.material.E)",
    ),
    "nu_changed": (
        lambda p: _edit(p, material={"law": "neo-hookean", "E": 4500.0, "nu": 0.3}),
        "material.nu 0.3 is not the 0.45",
    ),
    "max_force_changed": (
        lambda p: _training(p, max_force=600.0),
        "training.load_distribution.max_force 600.0 is not the 60.0 of the scene it was built from",
    ),
    "steps_changed": (lambda p: _training(p, steps=1), "(scene.training.load_steps)"),
    "no_scene": (lambda p: _edit(p, scene=None), "no 'scene' object"),
    "scene_without_material": (lambda p: _edit(p, scene={"name": "bar"}), "scene has no 'material' object"),
}


def _training(path, **changes):
    m = json.loads((path / "manifest.json").read_text())
    m["training"]["load_distribution"].update(changes)
    (path / "manifest.json").write_text(json.dumps(m))


def _network(path, **changes):
    m = json.loads((path / "manifest.json").read_text())
    m["network"].update(changes)
    (path / "manifest.json").write_text(json.dumps(m))


def _mesh(path, **changes):
    m = json.loads((path / "manifest.json").read_text())
    m["mesh"].update(changes)
    (path / "manifest.json").write_text(json.dumps(m))


@pytest.fixture
def store(bar_store, tmp_path):
    """A store with the good bar and one copy of it damaged each way in BAD."""
    root = tmp_path / "store"
    shutil.copytree(bar_store[0] / "bar", root / "bar")
    for name, (damage, _) in BAD.items():
        shutil.copytree(bar_store[0] / "bar", root / name)
        _edit(root / name, id=name if " " not in name else "a_list")
        damage(root / name)
    return root


def test_every_bad_entry_is_skipped_with_its_reason_and_the_good_one_loads(store, caplog):
    t0 = time.monotonic()
    with caplog.at_level(logging.ERROR, logger="service.store"):
        entries, errors = open_store(store)
    assert time.monotonic() - t0 < 60  # /dev/zero is never read
    assert set(entries) == {"bar"}
    assert set(errors) == set(BAD)
    for name, (_, words) in BAD.items():
        assert words in errors[name], (name, errors[name])
        assert "\n" not in errors[name], (name, errors[name])  # one line (torch's took one per tensor)
        said = [r for r in caplog.records if name in r.getMessage().split(":")[0]]
        assert len(said) == 1 and words in said[0].getMessage() and said[0].exc_info is None, name


def test_names_are_checked_before_any_file_is_read(store):
    """The hostile names are refused as names: loading them takes no time at all."""
    for name in ("dev_zero", "mesh_is_a_device", "mesh_is_a_fifo"):  # reading these would never end
        t0 = time.monotonic()
        with pytest.raises(StoreError):
            load_entry(store / name)
        assert time.monotonic() - t0 < 1.0


@pytest.mark.parametrize("fname", ["manifest.json", "mesh.npz"])
def test_a_file_swapped_for_a_fifo_after_its_check_is_refused_not_waited_on(bar_store, tmp_path, monkeypatch, fname):
    """Between the regular-file check and the read, another process may put a FIFO in the
    file's place: opening it for reading waited for a writer, and the server's start with it.
    The swap is made at that moment (right after the real check passes); the load runs in a
    thread so that a regression fails here rather than hangs."""
    import threading

    from service.store import load

    shutil.copytree(bar_store[0] / "bar", tmp_path / "bar")
    target = tmp_path / "bar" / fname
    checked = load._regular_file

    def check_then_swap(path, *args):
        checked(path, *args)
        if path == target:  # the race, made certain: the file is a FIFO by the time it is opened
            path.unlink()
            os.mkfifo(path)

    monkeypatch.setattr(load, "_regular_file", check_then_swap)
    outcome: list[BaseException | object] = []
    reader = threading.Thread(target=lambda: outcome.append(_outcome(load_entry, tmp_path / "bar")), daemon=True)
    reader.start()
    reader.join(timeout=10)
    if reader.is_alive():  # blocked in open(): a writer's open and close lets it go
        os.close(os.open(target, os.O_WRONLY | os.O_NONBLOCK))
        reader.join(timeout=10)
        pytest.fail(f"loading waited on the FIFO put in place of {fname}")
    assert isinstance(outcome[0], StoreError), outcome[0]
    assert str(outcome[0]) == f"bar: {fname} is not a regular file"


def _outcome(call, *args):
    """What `call` returned, or the exception it raised (for a thread to hand back)."""
    try:
        return call(*args)
    except Exception as exc:
        return exc


def _rewrite(entry, store, **changes):
    """write_entry with a loaded entry's own parts (and `changes` to them)."""
    from service.store import write_entry

    m = entry.manifest
    parts = dict(
        material=entry.network.material,
        scene=m["scene"],
        training=m["training"],
        network={k: v for k, v in m["network"].items() if k != "parameters"},
        rebuild=m["rebuild"],
    )
    parts.update(changes)
    return write_entry(store, entry.id, entry.mesh, entry.region, entry.network.net, **parts)


def test_a_full_disk_under_the_store_is_an_os_error_that_names_the_file(bar_store, tmp_path):
    """safetensors raised its own SafetensorError ("I/O error: No space left on device"), which
    `elastreg train` printed as a traceback, exit 1: now an OSError naming the entry's file (the
    CLI's one line, exit 2), and no half-written build left behind."""
    built = bar_store[0] / "bar"
    mesh_bytes, weights_bytes = (built / "mesh.npz").stat().st_size, (built / "weights.safetensors").stat().st_size
    room = -(-mesh_bytes // 4096) * 4096 + 4096  # the mesh fits, the weights do not
    assert weights_bytes > room
    with small_disk(tmp_path / "disk", room) as disk:
        with pytest.raises(OSError) as caught:
            _rewrite(load_entry(built), disk / "store")
        assert caught.value.errno == errno.ENOSPC
        assert caught.value.filename == str(disk / "store" / "bar" / "weights.safetensors")
        assert "No space left on device" in str(caught.value) and "\n" not in str(caught.value)
        assert list((disk / "store").iterdir()) == []  # the build folder went


def test_an_entry_the_store_would_refuse_never_replaces_the_served_one(bar_store, tmp_path):
    root = tmp_path / "store"
    shutil.copytree(bar_store[0] / "bar", root / "bar")
    before = (root / "bar" / "manifest.json").read_bytes()
    entry = load_entry(root / "bar")
    wrong = {**entry.manifest["network"], "n_in": 1}
    wrong.pop("parameters")
    with pytest.raises(StoreError, match="the weights do not fit the manifest"):
        _rewrite(entry, root, network=wrong)
    assert (root / "bar" / "manifest.json").read_bytes() == before
    assert [p.name for p in root.iterdir()] == ["bar"]  # no temporary left behind
    assert _rewrite(entry, root) == root / "bar"  # a good one does replace it
    assert load_entry(root / "bar").manifest["created"]


@pytest.mark.parametrize("kind", ["file", "link"])
def test_a_file_or_link_under_the_entrys_id_is_refused_and_left_where_it_is(bar_store, tmp_path, kind, capsys):
    """A file (or a symbolic link to an entry kept elsewhere) under the id was swapped out of the
    way, failed to be removed (errors ignored) and left for ever as .bar-XXXXXXXX.build: the
    user's file hidden, litter no clean-up takes. Now refused in one line, nothing moved."""
    from service.cli import main

    root = tmp_path / "store"
    root.mkdir()
    elsewhere = tmp_path / "elsewhere" / "bar"
    shutil.copytree(bar_store[0] / "bar", elsewhere)
    if kind == "file":
        (root / "bar").write_text("my notes")
    else:
        (root / "bar").symlink_to(elsewhere)
    with pytest.raises(ValueError, match=rf"^{re.escape(str(root / 'bar'))} is a (file|symbolic link), not an entry"):
        _rewrite(load_entry(elsewhere), root)
    assert [p.name for p in root.iterdir()] == ["bar"]  # nothing moved, no build folder left
    assert (root / "bar").is_symlink() == (kind == "link")
    assert kind == "link" or (root / "bar").read_text() == "my notes"
    # the build refuses it before any data: one line, exit 2
    scene = bar_store[0].parent / "scene" / "bar.toml"
    argv = ["train", str(scene), "--store", str(root), "--data", str(tmp_path / "data"), "--workers", "0"]
    capsys.readouterr()
    assert main(argv) == 2
    assert (
        capsys.readouterr().err == f"error: {root / 'bar'} is a {'file' if kind == 'file' else 'symbolic link'}, "
        "not an entry's folder: move it out of the store or build under another id\n"
    )
    assert [p.name for p in root.iterdir()] == ["bar"] and not (tmp_path / "data").exists()


def test_a_failed_swap_puts_the_served_entry_back(bar_store, tmp_path, monkeypatch):
    """Between the two renames a failure (a full disk, a concurrent writer) must not leave the
    store without the entry it served."""
    import service.store.write as write_module

    root = tmp_path / "store"
    shutil.copytree(bar_store[0] / "bar", root / "bar")
    before = (root / "bar" / "manifest.json").read_bytes()
    entry = load_entry(root / "bar")
    real = os.replace
    calls = []

    def second_fails(src, dst):
        calls.append((src, dst))
        if len(calls) == 2:  # the new entry into place
            raise OSError(39, "Directory not empty")
        return real(src, dst)

    monkeypatch.setattr(
        write_module, "_exchanged", lambda a, b: False
    )  # a system without renameat2 (patched where write_entry looks it up)
    monkeypatch.setattr(write_module.os, "replace", second_fails)
    with pytest.raises(OSError, match="not empty"):
        _rewrite(entry, root)
    monkeypatch.undo()
    assert (root / "bar" / "manifest.json").read_bytes() == before
    assert [p.name for p in root.iterdir()] == ["bar"]
    load_entry(root / "bar")


def test_a_replaced_entry_never_leaves_its_folder(bar_store, tmp_path, monkeypatch):
    """The new entry and the served one change places in one step: a process killed at any
    moment leaves the store serving one of them, never neither."""
    import service.store.write as write_module

    root = tmp_path / "store"
    shutil.copytree(bar_store[0] / "bar", root / "bar")
    entry = load_entry(root / "bar")
    moved = []
    real = os.replace
    monkeypatch.setattr(write_module.os, "replace", lambda a, b: (moved.append(a), real(a, b))[1])
    _rewrite(entry, root)
    assert root / "bar" not in moved  # never renamed away, even for a moment
    assert [p.name for p in root.iterdir()] == ["bar"]
    assert load_entry(root / "bar").manifest["created"]


@pytest.mark.skipif(os.name != "posix", reason="file modes")
@pytest.mark.parametrize(
    ("umask", "folder", "files"), [(0o022, 0o755, 0o644), (0o077, 0o700, 0o600)], ids=["022", "077"]
)
def test_an_entry_goes_in_with_the_modes_the_umask_gives(bar_store, tmp_path, monkeypatch, umask, folder, files):
    """A build's folder came from mkdtemp (0700) and its weights from safetensors (0600): a store
    built by one user was refused, Permission denied, by the server running as another. Now the
    entry has a plain mkdir's and open's modes under the umask, already when it is renamed in."""
    import service.store.write as write_module

    root = tmp_path / "store"
    root.mkdir()
    entry = load_entry(bar_store[0] / "bar")
    names = ("manifest.json", "mesh.npz", "weights.safetensors")
    wanted = {".": folder, **dict.fromkeys(names, files)}

    def modes(path) -> dict:
        return {name: stat.S_IMODE(os.stat(path / name).st_mode) for name in (".", *names)}

    seen = []
    real = os.replace
    monkeypatch.setattr(write_module.os, "replace", lambda a, b: (seen.append(modes(Path(a))), real(a, b))[1])
    old = os.umask(umask)
    try:
        _rewrite(entry, root)
    finally:
        os.umask(old)
    assert seen == [wanted]  # as it went in, not set after the rename
    assert modes(root / "bar") == wanted


@pytest.mark.skipif(os.name != "posix" or os.geteuid() != 0, reason="root gives the entry to another user")
def test_an_entry_one_user_built_is_served_to_another(bar_store, tmp_path):
    """The reviewer's case: built under umask 022, owned by another user (uid 65534), opened by a
    process that file modes bind (root without its override, as in _without_root_override)."""
    import subprocess
    import sys

    root = tmp_path / "store"
    old = os.umask(0o022)
    try:
        _rewrite(load_entry(bar_store[0] / "bar"), root)
    finally:
        os.umask(old)
    for path in (root / "bar", *(root / "bar").iterdir()):
        os.chown(path, 65534, 65534)
    script = (
        "import json, sys; from service.store import open_store; "
        "entries, errors = open_store(sys.argv[1]); print(json.dumps([list(entries), errors]))"
    )
    run = subprocess.run(_without_root_override([sys.executable, "-c", script, str(root)]), capture_output=True,
                         text=True, timeout=120)  # fmt: skip
    assert run.returncode == 0 and json.loads(run.stdout) == [["bar"], {}], run.stdout + run.stderr


def test_an_entry_a_killed_build_left_aside_is_served_again(bar_store, tmp_path, caplog):
    """Where the atomic exchange is missing, a build moves the served entry aside before its own
    goes in; killed between the two, it left the store without the model. The store puts it back."""
    root = tmp_path / "store"
    shutil.copytree(bar_store[0] / "bar", root / "..bar-k7x2q9_a")
    entries, errors = open_store(root)
    assert list(entries) == ["bar"] and not errors
    assert [p.name for p in root.iterdir()] == ["bar"]
    assert "restored the entry a build had moved aside" in caplog.text


def test_a_store_path_that_is_missing_or_a_file_is_named_as_such(tmp_path, caplog):
    a_file = tmp_path / "store.txt"
    a_file.write_text("not a store")
    with caplog.at_level("WARNING"):
        assert open_store(tmp_path / "nowhere") == ({}, {})
        assert open_store(a_file) == ({}, {})
    assert "nowhere does not exist" in caplog.text and "store.txt is not a folder" in caplog.text


def _rehash(path) -> None:
    """The manifest's checksums made to match the files as they now are: the damage reaches the
    loader's later checks, as a file corrupted before the manifest was written would."""
    from service.store import sha256

    m = json.loads((path / "manifest.json").read_text())
    m["files"] = {name: sha256(path / name) for name in m["files"]}
    (path / "manifest.json").write_text(json.dumps(m))


def _pickled(path) -> None:
    import torch

    torch.save({"x": torch.zeros(3)}, path / "weights.safetensors")


CORRUPT = {  # under checksums that match: the files' own formats must refuse them
    "weights_truncated": (lambda p: _truncate(p / "weights.safetensors"), "weights.safetensors is not a readable"),
    "weights_empty": (lambda p: (p / "weights.safetensors").write_bytes(b""), "weights.safetensors is not a readable"),
    "weights_pickled": (_pickled, "weights.safetensors is not a readable"),
    "mesh_truncated": (lambda p: _truncate(p / "mesh.npz"), "mesh.npz is unreadable"),
    # a diverged training's weights: every answer NaN (simulate's 200 of nulls, a frame's 422)
    "weights_nan": (lambda p: _poison(p / "weights.safetensors"), "weights.safetensors holds NaN or infinite values"),
}


def _poison(path) -> None:
    from safetensors.torch import load_file, save_file

    state = load_file(str(path))
    name = next(k for k, t in state.items() if t.is_floating_point() and t.ndim == 2)
    state[name][0, 0] = float("nan")
    save_file(state, str(path))


def _truncate(path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def test_a_corrupt_file_is_named_in_one_line_without_a_traceback(bar_store, tmp_path, caplog):
    """A truncated or foreign weights file or mesh whose checksum matches (safetensors' and zip's
    own errors) is a one-line reason naming the file: it was a traceback per entry in the log."""
    root = tmp_path / "store"
    shutil.copytree(bar_store[0] / "bar", root / "bar")
    for name, (damage, _) in CORRUPT.items():
        shutil.copytree(bar_store[0] / "bar", root / name)
        _edit(root / name, id=name)
        damage(root / name)
        _rehash(root / name)
    with caplog.at_level(logging.DEBUG, logger="service.store"):
        entries, errors = open_store(root)
    assert set(entries) == {"bar"} and set(errors) == set(CORRUPT)
    for name, (_, words) in CORRUPT.items():
        assert words in errors[name] and "\n" not in errors[name], errors[name]
        said = [r for r in caplog.records if r.levelno >= logging.ERROR and name in r.getMessage()]
        assert len(said) == 1 and said[0].exc_info is None, name  # once, and no traceback


@pytest.mark.skipif(os.name != "posix", reason="file modes")
def test_an_unreadable_file_is_named_in_one_line(bar_store, tmp_path):
    """chmod 000 on a manifest or the weights (a store copied with the wrong owner): one line
    naming the file. Root reads such files anyway, so as root the store is opened in a process
    without the capabilities that let it (setpriv)."""
    import subprocess
    import sys

    root = tmp_path / "store"
    shutil.copytree(bar_store[0] / "bar", root / "bar")
    for name in ("no_manifest", "no_weights"):
        shutil.copytree(bar_store[0] / "bar", root / name)
        _edit(root / name, id=name)
    (root / "no_manifest" / "manifest.json").chmod(0)
    (root / "no_weights" / "weights.safetensors").chmod(0)
    script = "import json, sys; from service.store import open_store; print(json.dumps(open_store(sys.argv[1])[1]))"
    run = subprocess.run(_without_root_override([sys.executable, "-c", script, str(root)]), capture_output=True,
                         text=True, timeout=120)  # fmt: skip
    assert run.returncode == 0, run.stderr
    errors = json.loads(run.stdout)
    assert set(errors) == {"no_manifest", "no_weights"}
    assert "manifest.json cannot be read (Permission denied)" in errors["no_manifest"]
    assert "weights.safetensors cannot be read (Permission denied)" in errors["no_weights"]
    assert "Traceback" not in run.stderr, run.stderr


#: a server's life in one process: the entry loaded and used, its weights file damaged in place
#: (the same inode), the entry used again; prints whether both answers are the same
_DAMAGED_UNDER_IT = """
import json, os, sys
from pathlib import Path
import numpy as np
from service.store import load_entry
entry = load_entry(Path(sys.argv[1]))
support = entry.region[:12]
forces = np.tile([0.0, 0.5, 1.0], (1, support.size, 1))
before = entry.network.predict(forces, support)
weights = Path(sys.argv[1]) / "weights.safetensors"
if sys.argv[2] == "truncate":
    os.truncate(weights, 0)
else:  # every byte past the header inverted: a valid header over other tensors
    with open(weights, "r+b") as f:
        start = 8 + int.from_bytes(f.read(8), "little")
        f.seek(start)
        rest = np.frombuffer(f.read(), np.uint8)
        f.seek(start)
        f.write((rest ^ 0xFF).tobytes())
after = entry.network.predict(forces, support)
print(json.dumps(bool(np.array_equal(before, after))))
"""


@pytest.mark.parametrize("damage", ["truncate", "overwrite"])
def test_a_weights_file_damaged_under_a_loaded_entry_changes_nothing_it_serves(tmp_path, damage):
    """The tensors were a memory map of weights.safetensors: truncating it under a running
    server killed the process (SIGBUS), and overwriting it in place changed its answers. The
    entry is built from the bytes it checked, so neither reaches it (the victim in a process of
    its own)."""
    import subprocess
    import sys

    shutil.copytree(Path(__file__).resolve().parents[1] / "model_store" / "phantom", tmp_path / "phantom")
    run = subprocess.run([sys.executable, "-c", _DAMAGED_UNDER_IT, str(tmp_path / "phantom"), damage],
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    assert run.returncode == 0, f"exit status {run.returncode}: {run.stderr[-2000:]}"
    assert json.loads(run.stdout) is True, "the loaded entry's answer changed with the file"


def _without_root_override(argv: list[str]) -> list[str]:
    """`argv` as a process that file modes bind: root reads and writes anything, so as root it
    runs without the capabilities that let it (setpriv); skipped where setpriv is missing."""
    if os.geteuid() != 0:
        return argv
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("root reads and writes any file, and setpriv (util-linux) is not here to drop that")
    return [setpriv, "--bounding-set", "-dac_override,-dac_read_search", *argv]


def _swap_mesh(path, **arrays) -> None:
    """mesh.npz rewritten with these arrays (the others as they were), and the manifest's
    checksums and mesh hash made to match it: the file is consistent with the manifest, so only
    a check of the mesh against the weights can tell."""
    from service.mesh import TetMesh

    with np.load(path / "mesh.npz") as z:
        mesh = {**dict(z), **arrays}
    np.savez(path / "mesh.npz", **mesh)
    m = json.loads((path / "manifest.json").read_text())
    m["mesh"]["hash"] = TetMesh(mesh["nodes"], mesh["tets"], mesh["fixed"]).hash
    (path / "manifest.json").write_text(json.dumps(m))
    _rehash(path)


def _shipped_beam_mesh() -> dict:
    from pathlib import Path

    with np.load(Path(__file__).resolve().parents[1] / "model_store" / "beam" / "mesh.npz") as z:
        return dict(z)


MISFITS = {
    "another_mesh": (lambda p: _swap_mesh(p, **_shipped_beam_mesh()), "mesh.npz does not fit weights.safetensors"),
    "region_out_of_range": (lambda p: _swap_mesh(p, region=np.array([0, 1, 10**6])), "region names nodes outside"),
    "region_negative": (lambda p: _swap_mesh(p, region=np.array([-1, 0])), "region names nodes outside"),
    "region_floats": (lambda p: _swap_mesh(p, region=np.array([0.5, 1.5])), "region must be a list of node ids"),
    "region_repeats": (lambda p: _swap_mesh(p, region=np.array([0, 0, 1])), "region repeats"),
}


def test_a_mesh_that_does_not_fit_the_weights_is_refused(bar_store, tmp_path):
    """Another model's mesh.npz (or a region the mesh has no nodes for) under a manifest made to
    match it: loaded before, and the model's first frame was a 500 (an IndexError, or torch's
    'mat1 and mat2 shapes cannot be multiplied'). Refused, naming both files."""
    root = tmp_path / "store"
    shutil.copytree(bar_store[0] / "bar", root / "bar")
    for name, (damage, _) in MISFITS.items():
        shutil.copytree(bar_store[0] / "bar", root / name)
        _edit(root / name, id=name)
        damage(root / name)
    entries, errors = open_store(root)
    assert set(entries) == {"bar"} and set(errors) == set(MISFITS)
    for name, (_, words) in MISFITS.items():
        assert words in errors[name], (name, errors[name])


def test_a_copy_under_another_folder_name_never_takes_the_models_place(bar_store, tmp_path):
    """A backup of bar (aaa_backup/, whose manifest says "bar") sorts before bar/: it was served
    as bar and bar/ itself refused as a "duplicate model id". A symbolic link to the entry under
    another name did the same. Each folder is served only under its own name."""
    root = tmp_path / "store"
    shutil.copytree(bar_store[0] / "bar", root / "bar")
    shutil.copytree(bar_store[0] / "bar", root / "aaa_backup")
    (root / "a_link").symlink_to(root / "bar", target_is_directory=True)
    entries, errors = open_store(root)
    assert list(entries) == ["bar"] and entries["bar"].path == root / "bar"
    assert set(errors) == {"aaa_backup", "a_link"}
    for name in errors:
        assert "says it is model 'bar'" in errors[name], errors[name]


def test_a_killed_builds_folder_is_removed_and_a_live_ones_kept(tmp_path, caplog):
    """A build killed mid-write (SIGKILL, a power cut) left its .ID-XXXXXXXX folder, weights and
    all, in the store for ever. Folders whose writer is alive, or which are not a build's, stay."""
    root = tmp_path / "store"
    root.mkdir()
    others = {  # a user's hidden folders, a build's folder from before the lock, an aside entry
        ".backup-20240101": "d", ".notes": "f", ".bar-k7x2q9_a": "d", "..bar-k7x2q9_a": "d", ".git": "d",
    }  # fmt: skip
    for name, kind in others.items():
        (root / name).mkdir() if kind == "d" else (root / name).write_text("mine")
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "keep").write_text("mine")
    (root / ".bar-linkedto.build").symlink_to(outside)  # a build folder's name, but a link: never followed
    with build_writer(root) as (live, live_name), build_writer(root) as (dead, dead_name):
        assert (root / live_name).is_dir() and (root / dead_name).is_dir() and live_name != dead_name
        os.kill(dead.pid, signal.SIGKILL)
        dead.wait(timeout=30)
        with caplog.at_level(logging.WARNING, logger="service.store"):
            assert remove_stale_builds(root) == [dead_name]
        assert not (root / dead_name).exists()
        assert (root / live_name / "weights.safetensors").stat().st_size == 1 << 16  # its writer lives
        said = [r.getMessage() for r in caplog.records if "removed" in r.getMessage()]
        assert said == [f"model store {root}: removed {dead_name}, the folder of a build whose process is gone"]
        assert sorted(p.name for p in root.iterdir()) == sorted([*others, ".bar-linkedto.build", live_name])
        open_store(root)  # serve's startup scan (which also puts the aside entry back, by its own rule)
        assert (root / live_name).is_dir()
        os.kill(live.pid, signal.SIGKILL)
        live.wait(timeout=30)
        open_store(root)
        assert not (root / live_name).exists()
    others = {"bar" if name == "..bar-k7x2q9_a" else name for name in others}
    assert sorted(p.name for p in root.iterdir()) == sorted([*others, ".bar-linkedto.build"])
    assert (outside / "keep").read_text() == "mine"


@pytest.mark.skipif(os.name != "posix", reason="file modes")
def test_a_read_only_store_keeps_its_stale_builds_with_one_warning_and_serves(bar_store, tmp_path):
    """A store served read-only logged an ERROR per stale build folder at every start, after
    emptying each (rmtree removed its files, then not the folder): now they stay as they are,
    one warning says how many and how to clean them, and the models are served."""
    import subprocess
    import sys

    root = tmp_path / "store"
    shutil.copytree(bar_store[0] / "bar", root / "bar")
    stale = [".bar-0a1b2c3d.build", ".bar-k7x2q9_a.build"]  # no process holds their lock
    for name in stale:
        (root / name).mkdir()
        (root / name / "weights.safetensors").write_bytes(bytes(1 << 10))
    script = (
        "import json, logging, sys; from service.store import open_store; "
        "logging.basicConfig(format='%(levelname)s %(message)s'); print(json.dumps(list(open_store(sys.argv[1])[0])))"
    )
    root.chmod(0o555)
    try:
        run = subprocess.run(_without_root_override([sys.executable, "-c", script, str(root)]), capture_output=True,
                             text=True, timeout=120)  # fmt: skip
    finally:
        root.chmod(0o755)
    assert run.returncode == 0 and json.loads(run.stdout) == ["bar"], run.stderr
    assert run.stderr.splitlines() == [
        f"WARNING model store {root} is read-only here: 2 stale build folder(s) left ({', '.join(stale)}); remove "
        "them as a user who can write it, by hand once no build runs or by `elastreg serve` or a build into it"
    ]
    for name in stale:
        assert (root / name / "weights.safetensors").stat().st_size == 1 << 10  # untouched


def test_an_unlocked_build_folder_is_removed_once_a_day_old_and_holding_only_an_entrys_files(tmp_path, caplog):
    """Build folders from before the lock (.ID-XXXXXXXX, no .build) were never removed, weights
    and all. With no lock to ask, one goes only when nothing in it has changed for a day and it
    holds nothing but an entry's files, cut off (here a manifest that is not JSON): a live build
    (no locks here) fills its folder in seconds. An empty one stays: nothing shows it a build's."""
    root = tmp_path / "store"
    root.mkdir()
    now = time.time()
    old, recent = now - UNLOCKED_BUILD_AGE_S - 3600, now - UNLOCKED_BUILD_AGE_S + 3600
    entry_files = ["manifest.json", "mesh.npz", "weights.safetensors"]

    def folder(name: str, files: list[str], when: float, touched: float | None = None) -> None:
        path = root / name
        path.mkdir()
        for f in files:
            (path / f).mkdir() if f.endswith("/") else (path / f).write_bytes(bytes(1 << 10))
        for inside in path.iterdir():
            os.utime(inside, (when, when))
        if touched is not None:  # one file written since
            os.utime(path / files[-1], (touched, touched))
        os.utime(path, (when, when))

    folder(".bar-k7x2q9_a", entry_files, old)  # a build killed mid-write, before the lock
    folder(".bar-0a1b2c3d", [], old)  # empty: nothing to reclaim, nor to tell it from a user's
    folder(".bar-5f6g7h8i", entry_files[:2], recent)  # 23 h: kept
    folder(".liver-abcdefgh", entry_files, old, touched=now)  # a file written just now: kept
    folder(".backup-20240101", ["notes.txt"], old)  # a user's folder by the same pattern
    folder(".bar-zz9zz9zz", ["manifest.json", "bar/"], old)  # a user's copy of an entry inside
    outside = tmp_path / "outside"
    folder("../outside", entry_files, old)
    (root / ".bar-linked99").symlink_to(outside)  # the name, but a link: never followed
    with caplog.at_level(logging.WARNING, logger="service.store"):
        assert remove_stale_builds(root) == [".bar-k7x2q9_a"]
    assert sorted(p.name for p in root.iterdir()) == [
        ".backup-20240101", ".bar-0a1b2c3d", ".bar-5f6g7h8i", ".bar-linked99", ".bar-zz9zz9zz", ".liver-abcdefgh"
    ]  # fmt: skip
    assert sorted(p.name for p in outside.iterdir()) == entry_files
    said = [r.getMessage() for r in caplog.records]
    assert said == [f"model store {root}: removed .bar-k7x2q9_a, the folder of a build's write cut off"]


def _age(path, when: float) -> None:
    """`path` and everything in it last changed at `when`."""
    for inside in path.iterdir():
        os.utime(inside, (when, when))
    os.utime(path, (when, when))


def _cut_short(path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


CUT_OFF = {  # a build killed (or its power cut) mid-write under an older version's folder name
    ".bar-a1b2c3d4": lambda p: [(p / f).unlink() for f in ("weights.safetensors", "manifest.json")],  # mesh only
    ".bar-m3n4o5p6": lambda p: (p / "weights.safetensors").unlink(),  # weights missing
    ".bar-e5f6g7h8": lambda p: _cut_short(p / "manifest.json"),  # manifest truncated: not JSON
    ".bar-i9j0k1l2": lambda p: _cut_short(p / "weights.safetensors"),  # weights lost: checksum mismatch
}


def test_a_day_old_copy_whose_checksums_no_build_writes_is_kept(bar_store, tmp_path):
    """A copy under an old build-folder name whose manifest's checksums were edited (null, or
    upper-case hex) is unlike any manifest a build writes, so nothing shows it a cut-off write:
    kept. It counted as a checksum mismatch and was removed."""
    root = tmp_path / "store"
    shutil.copytree(bar_store[0] / "bar", root / "bar")
    old = time.time() - UNLOCKED_BUILD_AGE_S - 3600
    edits = {".bar-hand_mad": lambda d: None, ".bar-upper_hx": str.upper}
    for name, edit in edits.items():
        shutil.copytree(bar_store[0] / "bar", root / name)
        manifest = json.loads((root / name / "manifest.json").read_text())
        manifest["files"] = {f: edit(d) for f, d in manifest["files"].items()}
        (root / name / "manifest.json").write_text(json.dumps(manifest))
        _age(root / name, old)
    open_store(root)
    assert sorted(p.name for p in root.iterdir()) == sorted(["bar", *edits])


def test_a_users_backups_named_like_old_build_folders_are_kept_and_only_cut_off_writes_go(bar_store, tmp_path, caplog):
    """Any day-old .ID-XXXXXXXX holding an entry's files was removed at every store open: a
    user's `cp -a liver .liver-original` (tempfile's 8 characters are [a-z0-9_]: 'original',
    '20240501', 'old_copy' are such names) went with it. Now only a write shown to be cut off
    goes; a complete entry under such a name stays, with one warning naming it, and loads."""
    root = tmp_path / "store"
    shutil.copytree(bar_store[0] / "bar", root / "bar")
    old = time.time() - UNLOCKED_BUILD_AGE_S - 3600
    backups = [".liver-original", ".liver-previous", ".liver-20240501", ".liver-old_copy", ".bar-q7r8s9t0"]
    for name in backups:
        shutil.copytree(bar_store[0] / "bar", root / name)
        _age(root / name, old)
    (root / ".notes-abcdefgh").mkdir()  # a user's empty folder
    _age(root / ".notes-abcdefgh", old)
    for name, damage in CUT_OFF.items():
        shutil.copytree(bar_store[0] / "bar", root / name)
        damage(root / name)
        _age(root / name, old)
    with caplog.at_level(logging.WARNING, logger="service.store"):
        entries, errors = open_store(root)
    assert set(entries) == {"bar"} and errors == {}
    assert sorted(p.name for p in root.iterdir()) == sorted(["bar", ".notes-abcdefgh", *backups])
    for name in backups:  # untouched: each still loads as the entry it copies
        assert load_entry(root / name, name="bar").manifest["files"] == entries["bar"].manifest["files"]
    said = [r.getMessage() for r in caplog.records]
    assert sorted(said) == sorted(
        [f"model store {root}: removed {name}, the folder of a build's write cut off" for name in CUT_OFF]
        + [f"model store {root}: kept {name}: named like an older version's build folder, but it holds a complete "
           "entry (rename it if it is yours, remove it if not)" for name in backups]
    )  # fmt: skip


def test_a_manifest_claiming_a_huge_network_is_refused_before_it_is_built(bar_store, tmp_path):
    """A manifest edited (as a corrupt or hostile store's may be) to claim hidden layers 2e6 wide
    over the bar's small weights: the network was built from it (635 MiB), and only then
    compared with the weights. Now the layout is compared on the meta device first: refused,
    naming the entry, the file and the mismatch, with no more memory than a good entry takes
    (peak RSS, measured in a process of its own)."""
    import subprocess
    import sys

    root = tmp_path / "store"
    shutil.copytree(bar_store[0] / "bar", root / "bar")
    shutil.copytree(bar_store[0] / "bar", root / "huge")
    _edit(root / "huge", id="huge")
    _network(root / "huge", hidden=[2_000_000, 64])
    script = (
        "import json, resource, sys; from service.store import StoreError, load_entry\n"
        "peak = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024\n"
        "load_entry(sys.argv[1] + '/bar'); before = peak()\n"  # a good entry's cost first
        "try:\n    load_entry(sys.argv[1] + '/huge'); error = None\n"
        "except StoreError as exc:\n    error = str(exc)\n"
        "print(json.dumps([peak() - before, error]))"
    )
    run = subprocess.run([sys.executable, "-c", script, str(root)], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    grew_mib, error = json.loads(run.stdout)
    assert error is not None and error.startswith("huge: the weights do not fit the manifest (weights.safetensors:")
    assert "[2000000] in the network" in error
    assert grew_mib < 100, f"refusing the manifest took {grew_mib:.0f} MiB"


def test_a_manifest_claiming_more_members_or_layers_than_its_weights_is_refused_before_any_layout(tmp_path):
    """The shipped phantom's manifest edited to claim 20000 ensemble members, or 20000 hidden
    layers: each was laid out module by module (on the meta device) before the refusal, members
    100000 taking 123 s and 2.6 GB. The counts are compared with the weights' tensor names
    first: refused naming the entry, the file and the mismatch, with no more memory than a good
    entry takes (peak RSS, in a process of its own). The manifest is hashed nowhere: the
    files' checksums stand."""
    import subprocess
    import sys

    shipped = Path(__file__).resolve().parents[1] / "model_store" / "phantom"
    root = tmp_path / "store"
    shutil.copytree(shipped, root / "phantom")
    claims = {"members": {"members": 20000}, "layers": {"hidden": [8] * 20000}}
    for name, claim in claims.items():
        shutil.copytree(shipped, root / name)
        _edit(root / name, id=name)
        _network(root / name, **claim)
    script = (
        "import json, resource, sys; from service.store import StoreError, load_entry\n"
        "peak = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024\n"
        "load_entry(sys.argv[1] + '/phantom'); before = peak(); errors = []\n"  # a good entry's cost first
        "for name in ('members', 'layers'):\n"
        "    try:\n        load_entry(sys.argv[1] + '/' + name); errors.append(None)\n"
        "    except StoreError as exc:\n        errors.append(str(exc))\n"
        "print(json.dumps([peak() - before, errors]))"
    )
    run = subprocess.run([sys.executable, "-c", script, str(root)], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    grew_mib, (members, layers) = json.loads(run.stdout)
    prefix = "the weights do not fit the manifest (weights.safetensors: the manifest's network"
    assert members == f"members: {prefix}.members is 20000, the file holds 1 member(s))"
    assert layers == (f"layers: {prefix}.hidden has 20000 layers (20001 weight matrices per member), the file holds 3)")
    assert grew_mib < 100, f"refusing the manifests took {grew_mib:.0f} MiB"


@pytest.mark.parametrize("fname", ["weights.safetensors", "mesh.npz"])
def test_a_file_larger_than_an_entry_holds_is_refused_unread(bar_store, tmp_path, fname):
    """Each file is read whole into memory (the bytes checked are the bytes served): a sparse
    8 GiB file (no disk, all memory) is refused by its size before a byte of it is read."""
    from service.store import StoreError, load_entry
    from service.store.files import MAX_DATA_FILE

    shutil.copytree(bar_store[0] / "bar", tmp_path / "bar")
    os.truncate(tmp_path / "bar" / fname, 2 * MAX_DATA_FILE)  # sparse: no disk taken
    with pytest.raises(StoreError, match=rf"^bar: {re.escape(fname)} is over 4 GiB, more than an entry holds$"):
        load_entry(tmp_path / "bar")

"""Loading the store: every bad entry is skipped with a logged reason while the others load, and
the names in a manifest are checked before any file is read (a name like ``../../../dev/zero``
hung startup, hashing the endless device)."""

from __future__ import annotations

import json
import logging
import os
import shutil
import time

import pytest

from service.store import StoreError, load_entry, open_store


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
    "bad_hidden": (lambda p: _edit(p, network={"layout": "reduced", "n_in": 3, "hidden": 5}), "cannot be loaded"),
}


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
        assert any(name in r.getMessage() and words in r.getMessage() for r in caplog.records), name


def test_names_are_checked_before_any_file_is_read(store):
    """The hostile names are refused as names: loading them takes no time at all."""
    for name in ("dev_zero", "mesh_is_a_device", "mesh_is_a_fifo"):  # reading these would never end
        t0 = time.monotonic()
        with pytest.raises(StoreError):
            load_entry(store / name)
        assert time.monotonic() - t0 < 1.0


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


def test_a_failed_swap_puts_the_served_entry_back(bar_store, tmp_path, monkeypatch):
    """Between the two renames a failure (a full disk, a concurrent writer) must not leave the
    store without the entry it served."""
    import service.store as store_module

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

    monkeypatch.setattr(store_module, "_exchange", lambda a, b: False)  # a system without renameat2
    monkeypatch.setattr(store_module.os, "replace", second_fails)
    with pytest.raises(OSError, match="not empty"):
        _rewrite(entry, root)
    monkeypatch.undo()
    assert (root / "bar" / "manifest.json").read_bytes() == before
    assert [p.name for p in root.iterdir()] == ["bar"]
    load_entry(root / "bar")


def test_a_replaced_entry_never_leaves_its_folder(bar_store, tmp_path, monkeypatch):
    """The new entry and the served one change places in one step: a process killed at any
    moment leaves the store serving one of them, never neither."""
    import service.store as store_module

    root = tmp_path / "store"
    shutil.copytree(bar_store[0] / "bar", root / "bar")
    entry = load_entry(root / "bar")
    moved = []
    real = os.replace
    monkeypatch.setattr(store_module.os, "replace", lambda a, b: (moved.append(a), real(a, b))[1])
    _rewrite(entry, root)
    assert root / "bar" not in moved  # never renamed away, even for a moment
    assert [p.name for p in root.iterdir()] == ["bar"]
    assert load_entry(root / "bar").manifest["created"]


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

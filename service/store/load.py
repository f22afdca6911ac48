"""Loading: one entry, verified file by file into both forward models, or a whole store, each
entry isolated from the others."""

from __future__ import annotations

import dataclasses
import io
import json
import os
import stat
import zipfile
import zlib
from pathlib import Path

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load as load_tensors

from ..fem.material import NeoHookean
from ..fem.model import FEMModel
from ..mesh import TetMesh
from ..scene import MODEL_ID
from ..surrogate.model import NetworkModel
from .builds import _restore_aside, remove_stale_builds
from .files import _MAX_MANIFEST, MANIFEST, MAX_DATA_FILE, MESH, WEIGHTS, StoreError, log, sha256_of
from .manifest import _check_manifest, _max_force, _tool_patch
from .network import _check_fit, network_from_manifest


@dataclasses.dataclass(frozen=True, eq=False)
class Entry:
    """A loaded model: its manifest and both forward models over one mesh."""

    id: str
    path: Path
    manifest: dict = dataclasses.field(repr=False)
    mesh: TetMesh = dataclasses.field(repr=False)
    region: np.ndarray = dataclasses.field(repr=False)
    network: NetworkModel = dataclasses.field(repr=False)
    fem: FEMModel = dataclasses.field(repr=False)

    def model(self, method: str):
        if method == "network":
            return self.network
        if method == "fem":
            return self.fem
        raise ValueError(f"unknown method {method!r}; choose 'network' or 'fem'")

    def summary(self) -> dict:
        m = self.manifest
        return {
            "id": self.id,
            "n_nodes": self.mesh.n_nodes,
            "n_tets": self.mesh.n_tets,
            "n_surface_nodes": int(self.mesh.surface_nodes.size),
            "n_fixed_nodes": int(self.mesh.fixed.size),
            "n_region_nodes": int(self.region.size),
            "material": m["material"],
            "methods": ["network", "fem"],
            "training": m.get("training", {}),
            "network": m.get("network", {}),
            "mesh_renumbered": bool(m["mesh"].get("renumbered", False)),
            "bounding_box": self.mesh.bounding_box.tolist(),
            "created": m.get("created"),
            "code_version": m.get("code_version"),
        }


def _region(value: np.ndarray, n_nodes: int, name: str) -> np.ndarray:
    """The load region's node ids: distinct whole numbers in 0..n-1."""
    if value.ndim != 1 or value.dtype.kind not in "iu":
        raise StoreError(f"{name}: {MESH}'s region must be a list of node ids, got a {value.dtype} array {value.shape}")
    if value.size and (value.min() < 0 or value.max() >= n_nodes):
        raise StoreError(f"{name}: {MESH}'s region names nodes outside 0..{n_nodes - 1} (the mesh's)")
    if np.unique(value).size != value.size:
        raise StoreError(f"{name}: {MESH}'s region repeats node ids")
    return value.astype(np.int64)


def _regular_file(path: Path, folder: Path, name: str, fname: str, cap: int) -> None:
    """A StoreError unless ``path`` is a regular file inside ``folder`` (no device, pipe or link
    out of the entry) of at most ``cap`` bytes, checked without opening it."""
    try:
        inside = path.resolve().is_relative_to(folder.resolve())
        found = path.stat()
    except FileNotFoundError:
        raise StoreError(f"{name}: {fname} is missing") from None
    except OSError as exc:
        raise StoreError(f"{name}: {fname} cannot be read ({exc})") from None
    if not inside:
        raise StoreError(f"{name}: {fname} points outside the entry's folder")
    _refuse_unless_fits(found, name, fname, cap)


def _refuse_unless_fits(found: os.stat_result, name: str, fname: str, cap: int) -> None:
    """A StoreError unless what `found` describes is a regular file of at most `cap` bytes."""
    if not stat.S_ISREG(found.st_mode):
        raise StoreError(f"{name}: {fname} is not a regular file")
    if found.st_size > cap:
        size = f"{cap >> 30} GiB" if cap >= 1 << 30 else f"{cap >> 20} MiB"
        raise StoreError(f"{name}: {fname} is over {size}, more than an entry holds")


def _read_file(path: Path, name: str, fname: str, cap: int) -> bytes:
    """The bytes of the regular file at `path` (at most `cap`), judged by the file it opened: one
    swapped for a FIFO or a device after _regular_file's check is refused, never waited on."""
    try:  # O_NONBLOCK: opening a FIFO returns at once, with or without a writer
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        raise _unreadable(name, fname, exc) from None
    with open(fd, "rb") as f:
        found = os.fstat(fd)
        _refuse_unless_fits(found, name, fname, cap)
        try:  # one byte past the size fstat gave: a file growing since is caught, not read on
            data = f.read(found.st_size + 1)
        except OSError as exc:
            raise _unreadable(name, fname, exc) from None
    if len(data) > found.st_size:
        raise StoreError(f"{name}: {fname} grew while it was read (a build writing it?)")
    return data


def _unreadable(name: str, fname: str, exc: OSError) -> StoreError:
    """The system would not let us read a file (permissions, I/O): named, in one line."""
    return StoreError(f"{name}: {fname} cannot be read ({exc.strerror or exc})")


def _one_line(text: str, limit: int = 300) -> str:
    """An exception's text as one log line (torch's and NumPy's messages span several)."""
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def load_entry(path: Path, name: str | None = None) -> Entry:
    """Load and verify one entry; a :class:`StoreError` says what is wrong. `name`: the id it
    is to be served as (default: its folder's name)."""
    path = Path(path)
    name = path.name if name is None else name
    if not MODEL_ID.fullmatch(name):
        raise StoreError(f"{name!r:.80}: an entry's folder name must match {MODEL_ID.pattern}")
    _regular_file(path / MANIFEST, path, name, MANIFEST, _MAX_MANIFEST)
    try:
        manifest = json.loads(_read_file(path / MANIFEST, name, MANIFEST, _MAX_MANIFEST))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise StoreError(f"{name}: {MANIFEST} is not valid JSON ({exc})") from None
    _check_manifest(manifest, name)
    for fname in (MESH, WEIGHTS):  # every name and size checked before any file is read
        _regular_file(path / fname, path, name, fname, MAX_DATA_FILE)
    # each file read once: what is checked is what is served, and nothing keeps a map of the file
    # (a weights file truncated under a mapped server killed it with SIGBUS; one rewritten in place
    # changed its answers)
    data: dict[str, bytes] = {}
    for fname, digest in manifest["files"].items():
        data[fname] = _read_file(path / fname, name, fname, MAX_DATA_FILE)
        if sha256_of(data[fname]) != digest:
            raise StoreError(f"{name}: {fname} does not match its checksum in the manifest (corrupt or changed)")
    try:  # a zip of .npy arrays, read without pickle
        with np.load(io.BytesIO(data.pop(MESH)), allow_pickle=False) as z:
            arrays = {key: z[key] for key in ("nodes", "tets", "fixed", "region")}
    except (KeyError, ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise StoreError(f"{name}: {MESH} is unreadable ({_one_line(str(exc))})") from None
    try:
        mesh = TetMesh(arrays["nodes"], arrays["tets"], arrays["fixed"])
    except ValueError as exc:  # a MeshError is one
        raise StoreError(f"{name}: {MESH} does not hold a usable mesh ({_one_line(str(exc))})") from None
    region = _region(arrays["region"], mesh.n_nodes, name)
    if mesh.hash != manifest["mesh"].get("hash"):
        raise StoreError(f"{name}: the mesh does not match the hash recorded in the manifest")
    try:  # safetensors: a header and raw tensors, nothing a file could run (no pickle)
        state = load_tensors(data.pop(WEIGHTS))
    except SafetensorError as exc:  # truncated, empty, another format under this name
        raise StoreError(f"{name}: {WEIGHTS} is not a readable safetensors file ({exc})") from None
    broken = sorted(k for k, t in state.items() if t.is_floating_point() and not bool(torch.isfinite(t).all()))
    if broken:  # a training run that diverged: every answer would be NaN (a 200 of nulls, a frame's 422)
        raise StoreError(f"{name}: {WEIGHTS} holds NaN or infinite values (in {', '.join(broken[:3])})")
    material = NeoHookean.of(manifest["material"])  # checked by _check_manifest
    try:
        net = network_from_manifest(manifest["network"], state)
    except (KeyError, ValueError, RuntimeError) as exc:
        raise StoreError(f"{name}: the weights do not fit the manifest ({WEIGHTS}: {_one_line(str(exc))})") from None
    _check_fit(net, mesh, region, name)
    max_force, tool_patch = _max_force(manifest, name), _tool_patch(manifest, name)  # the estimate's prior
    network = NetworkModel(mesh, material, region, net, E0=material.E, max_force=max_force, tool_patch=tool_patch)
    fem = FEMModel(mesh, material, max_force=max_force, tool_patch=tool_patch)
    return Entry(manifest["id"], path, manifest, mesh, region, network, fem)


def check_store(store: Path) -> None:
    """A :class:`StoreError` unless ``store`` is a folder this process can list (``elastreg
    serve`` refuses to start over anything else: a typo in --store is not a server without
    models)."""
    store = Path(store)
    try:
        if not stat.S_ISDIR(os.stat(store).st_mode):
            raise StoreError(f"model store {store} is not a folder")
        with os.scandir(store) as listing:
            next(listing, None)
    except FileNotFoundError:
        raise StoreError(f"model store {store} does not exist") from None
    except OSError as exc:
        raise StoreError(f"model store {store} cannot be read ({exc.strerror or exc})") from None


def open_store(store: Path) -> tuple[dict[str, Entry], dict[str, str]]:
    """Every loadable entry by id, and the refused ones with the reason (each one logged). An
    entry is served under its folder's name, which must be its manifest's id: a copy of an entry
    under another name (a backup, a symbolic link) is refused, not served in its place."""
    store = Path(store)
    entries: dict[str, Entry] = {}
    errors: dict[str, str] = {}
    try:
        check_store(store)
    except StoreError as exc:
        log.error("%s", exc)
        return entries, errors
    _restore_aside(store)
    remove_stale_builds(store)
    for path in sorted(p for p in store.iterdir() if p.is_dir() and not p.name.startswith(".")):
        try:
            entry = load_entry(path)
        except StoreError as exc:
            log.error("skipping model %s", exc)
            errors[path.name] = str(exc)
            continue
        except Exception as exc:  # one entry never stops the others: skipped, with its reason
            msg = f"{path.name}: cannot be loaded ({type(exc).__name__}: {_one_line(str(exc))})"
            log.error("skipping model %s", msg)  # one line; the traceback only with DEBUG on
            log.debug("model %s: where loading it failed", path.name, exc_info=exc)
            errors[path.name] = msg
            continue
        if entry.id != path.name:  # else a copy (aaa_backup/, a link) would take the id's place by name order
            msg = (
                f"{path.name}: its {MANIFEST} says it is model {entry.id!r}; a model's folder must be named "
                "after its id (rename the folder, or set the id, for it to be served)"
            )
            log.error("skipping model %s", msg)
            errors[path.name] = msg
            continue
        entries[entry.id] = entry
        log.info("loaded model %s (%d nodes)", entry.id, entry.mesh.n_nodes)
    return entries, errors

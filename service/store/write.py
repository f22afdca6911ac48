"""Writing an entry: built and checked in a build folder, then swapped into place in one step,
with the modes the writer's umask gives."""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import stat
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import save_file

from .. import __version__
from ..fem.material import NeoHookean
from ..folders import exchange
from ..mesh import TetMesh
from ..scene import check_model_id
from .builds import _ASIDE, _build_folder
from .files import FORMAT_VERSION, MANIFEST, MESH, WEIGHTS, sha256
from .load import load_entry


def _exchanged(a: Path, b: Path) -> bool:
    """exchange(a, b), False where it failed (a mount point, say): the two renames then say what is wrong."""
    try:
        return exchange(a, b)
    except OSError:
        return False


def network_table(net: Any, layout: str, n_region: int, n_nodes: int) -> dict:
    """The manifest's `network` table of a trained `net` (the trainer's `layout`; Any: its
    attributes are the layout's own): what the store needs to rebuild it (network_from_manifest)."""
    features = int(net.feature_basis.shape[1]) if getattr(net, "physics", False) else None
    return {
        "layout": layout,
        "hidden": list(net.hidden),
        "n_in": features if features is not None else 3 * n_region,
        "n_out": 3 * n_nodes,
        "rank": int(net.basis.shape[1]) if hasattr(net, "basis") else None,
        "members": int(getattr(net, "members", 1)),
        "physics_skip": features is not None,
        "features": features,
    }


def check_entry_place(store: Path, entry_id: str) -> None:
    """Refuse (ValueError, nothing moved) where `store`/`entry_id` exists and is not a folder: a
    file or a symbolic link (even to an entry kept elsewhere) was swapped out of the way under a
    build folder's name and never removed, the user's file hidden for ever."""
    final = Path(store) / entry_id
    try:
        mode = os.lstat(final).st_mode
    except FileNotFoundError:
        return
    if stat.S_ISDIR(mode):
        return
    kind = "a symbolic link" if stat.S_ISLNK(mode) else "a file" if stat.S_ISREG(mode) else "not a folder"
    raise ValueError(f"{final} is {kind}, not an entry's folder: move it out of the store or build under another id")


def write_entry(
    store: Path,
    entry_id: str,
    mesh: TetMesh,
    region: np.ndarray,
    net: torch.nn.Module,
    *,
    material: NeoHookean,
    scene: dict,
    training: dict,
    network: dict,
    rebuild: str,
    renumbered: bool = False,
) -> Path:
    """Write an entry atomically: built in a temporary folder (.ID-XXXXXXXX.build, locked while
    this process writes it) and loaded back from it (an entry the store would refuse never
    replaces one it serves), then renamed into place, its folder and files readable as far as
    the process's umask lets them be (as any folder and file it creates)."""
    check_model_id(entry_id)
    store = Path(store)
    store.mkdir(parents=True, exist_ok=True)
    check_entry_place(store, entry_id)  # before the build folder: a refusal moves nothing
    final = store / entry_id
    tmp, lock = _build_folder(store, entry_id)
    try:
        with _naming(final / MESH):
            np.savez(
                tmp / MESH, nodes=mesh.nodes, tets=mesh.tets, fixed=mesh.fixed, region=np.asarray(region, np.int64)
            )
        state = {k: v.detach().cpu().contiguous() for k, v in net.state_dict().items()}
        with _naming(final / WEIGHTS):
            save_file(state, str(tmp / WEIGHTS), metadata={"elastreg": __version__})
        manifest = {
            "format_version": FORMAT_VERSION,
            "id": entry_id,
            "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "code_version": __version__,
            "scene": scene,
            "material": {"law": material.law, "E": material.E, "nu": material.nu},
            "mesh": {**mesh.summary(), "hash": mesh.hash, "renumbered": renumbered},
            "network": {**network, "parameters": int(sum(p.numel() for p in net.parameters()))},
            "training": training,
            "rebuild": rebuild,
            "files": {name: sha256(tmp / name) for name in (MESH, WEIGHTS)},
        }
        with _naming(final / MANIFEST):
            (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1, default=_jsonable))
        _share(tmp)  # before the rename: no moment where the served entry is private to its builder
        load_entry(tmp, name=entry_id)
        if not final.exists():
            os.replace(tmp, final)
        elif _exchanged(tmp, final):  # one atomic step: no moment, crash or not, without the entry
            shutil.rmtree(tmp, ignore_errors=True)  # it holds the entry it replaced
        else:  # two renames; a crash between them leaves the old entry aside, and open_store restores it
            old = Path(tempfile.mkdtemp(prefix=f"{_ASIDE}{entry_id}-", dir=store))
            os.replace(final, old)
            try:
                os.replace(tmp, final)
            except BaseException:
                if not final.exists():  # put the served entry back: never a store without it
                    os.replace(old, final)
                raise
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        if lock is not None:  # the folder is in place or gone: nothing left to guard
            os.close(lock)
    return final


@contextlib.contextmanager
def _naming(path: Path) -> Iterator[None]:
    """A failed write (a full disk) as an OSError that names the entry's file: a write through
    an open file names none, and safetensors raises its own SafetensorError ("I/O error: No
    space left on device (os error 28)")."""
    try:
        yield
    except SafetensorError as exc:
        code = re.search(r"os error (\d+)", str(exc))
        if code is None:
            raise OSError(f"cannot write {path}: {exc}") from exc
        raise OSError(int(code[1]), os.strerror(int(code[1])), str(path)) from exc
    except OSError as exc:
        if exc.filename is not None:
            raise
        raise OSError(exc.errno, exc.strerror, str(path)) from exc


def _umask() -> int:
    """The process's umask, read without changing it where Linux tells (os.umask sets it: a
    thread creating a file meanwhile gets the value set, so the stricter 0o077 is set)."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    mask = os.umask(0o077)
    os.umask(mask)
    return mask


def _share(folder: Path) -> None:
    """Give a build's folder and files the modes a plain mkdir and open would under the umask:
    mkdtemp makes it 0700 and safetensors writes 0600, and a store built by one user is served
    by another (a service account, the Docker image's USER, a read-only mount)."""
    mask = _umask()
    os.chmod(folder, 0o777 & ~mask)
    for name in (MANIFEST, MESH, WEIGHTS):
        os.chmod(folder / name, 0o666 & ~mask)


def _jsonable(x):
    if isinstance(x, (np.integer, np.floating)):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")

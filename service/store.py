"""The model store: one folder per trained model, checked before it is trusted.

    <store>/<id>/manifest.json        what it is: scene, material, mesh facts, network layout,
                                      training figures, validation metrics, code version,
                                      the command that rebuilds it, and a SHA-256 per file
    <store>/<id>/mesh.npz             nodes, tets, fixed nodes, the load region
    <store>/<id>/weights.safetensors  the network's tensors (normalisation buffers included)
    <store>/.<id>-XXXXXXXX.build/     a build writing its entry (locked by that process; stale
                                      ones, whose writer is gone, are removed: remove_stale_builds)
    <store>/.<id>-XXXXXXXX/           the same, unlocked (older versions; file systems without
                                      locks): removed once a day old and shown to be a write cut
                                      off (a complete entry under such a name is kept)

Loading checks the manifest's shape and every name in it before any other file is opened (the
file names must be exactly the two above, regular files inside the entry's folder: a manifest
naming ``../../../dev/zero`` is refused without reading it; what it records twice, the material
and load distribution it serves beside its scene's, must agree), re-hashes every file against the
manifest and the mesh arrays against the recorded mesh hash, builds the network from the
manifest and loads the weights strictly; any mismatch, and any file the system will not let us
read or whose own format refuses it, is a :class:`StoreError` naming the entry, the file and
what is wrong. :func:`open_store` isolates entries: whatever goes wrong with one (a StoreError,
or any other exception) skips it with one logged line while the others load (the traceback of
an unexpected exception only at DEBUG). Weights are read with safetensors: no pickle anywhere.
An entry goes in with the modes the writer's umask gives a new folder and file: another user
serves what one builds.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import hashlib
import json
import logging
import math
import os
import re
import shutil
import stat
import tempfile
import time
import zipfile
import zlib
from pathlib import Path

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

try:  # advisory locks: POSIX systems
    import fcntl
except ImportError:  # pragma: no cover - Windows: builds write unlocked, nothing is taken for stale
    fcntl = None  # type: ignore[assignment]

from . import __version__
from .fem.material import NeoHookean
from .fem.model import FEMModel
from .mesh import TetMesh
from .scene import MODEL_ID, check_model_id
from .surrogate.model import NetworkModel
from .surrogate.network import PaperSurrogate, ReducedSurrogate

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
MANIFEST = "manifest.json"
MESH = "mesh.npz"
WEIGHTS = "weights.safetensors"
_MAX_MANIFEST = 1 << 20  # bytes


class StoreError(RuntimeError):
    """An entry that cannot be used, and why."""


def sha256(path: Path) -> str:
    with open(path, "rb") as f:
        return _digest(f)


def _digest(f) -> str:
    """The SHA-256 of an open binary file, read from where it stands to its end."""
    h = hashlib.sha256()
    for chunk in iter(lambda: f.read(1 << 20), b""):
        h.update(chunk)
    return h.hexdigest()


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


def network_from_manifest(spec: dict, state: dict[str, torch.Tensor]) -> torch.nn.Module:
    """Rebuild the module the manifest describes (shapes come from the saved tensors). A
    ValueError in one line when the tensors do not fit it (``spec`` checked by _check_network)."""
    layout = spec.get("layout")
    if layout == "reduced":
        basis = state.get("basis")
        if basis is None or basis.ndim != 2:
            raise ValueError("no 'basis' matrix among its tensors" if basis is None else "its 'basis' is not a matrix")
        net: torch.nn.Module = ReducedSurrogate(
            int(spec["n_in"]), basis, [int(h) for h in spec["hidden"]], members=int(spec.get("members", 1)),
            feature_basis=state.get("feature_basis"),  # the physics layout's (older entries: none)
        )  # fmt: skip
    elif layout == "paper":
        net = PaperSurrogate(int(spec["n_in"]), int(spec["n_out"]), depth=len(spec["hidden"]) + 1)
    else:
        raise StoreError(f"unknown network layout {layout!r}")
    mismatch = _state_mismatch(net.state_dict(), state)
    if mismatch:
        raise ValueError(mismatch)
    net.load_state_dict(state, strict=True)
    return net.eval()


def _state_mismatch(wanted: dict[str, torch.Tensor], got: dict[str, torch.Tensor]) -> str | None:
    """What differs between the tensors a network needs and those a file holds, in one line
    (torch's own message takes a line per tensor); None when they fit."""

    def some(names) -> str:
        names = sorted(names)
        return ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")

    parts = []
    missing, extra = wanted.keys() - got.keys(), got.keys() - wanted.keys()
    if missing:
        parts.append(f"{len(missing)} missing ({some(missing)})")
    if extra:
        parts.append(f"{len(extra)} not in the network ({some(extra)})")
    shaped = sorted(k for k in wanted.keys() & got.keys() if wanted[k].shape != got[k].shape)
    if shaped:
        k = shaped[0]
        parts.append(
            f"{len(shaped)} of another shape ({k}: {list(got[k].shape)} in the file, {list(wanted[k].shape)} "
            f"in the network{' ...' if len(shaped) > 1 else ''})"
        )
    return "tensors " + "; ".join(parts) if parts else None


#: an entry moved aside while its replacement goes in: ..ID-XXXXXXXX (no build's temporary
#: folder, .ID-XXXXXXXX.build, nor any entry starts so)
_ASIDE = ".."
#: a build's temporary folder ends so: a hidden folder of the user's is never taken for one
_BUILDING = ".build"
#: tempfile.mkdtemp's 8 random characters ([a-z0-9_]), which every version's build folder takes
_RANDOM = "[a-z0-9_]{8}"
_BUILD_FOLDER = re.compile(rf"\.{MODEL_ID.pattern.strip('^$')}-{_RANDOM}{re.escape(_BUILDING)}")
#: a build's folder with no lock: written before the lock came in (ea8e4fa), or where the file
#: system has none (_build_folder). A user's `.liver-original` or `.liver-20240501` has such a
#: name too: only a write cut off (_cut_off) is ever removed
_UNLOCKED_BUILD_FOLDER = re.compile(rf"\.{MODEL_ID.pattern.strip('^$')}-{_RANDOM}")
#: an unlocked build folder untouched this long has no writer: write_entry fills one in seconds
UNLOCKED_BUILD_AGE_S = 24 * 3600.0


def _lock(fd: int) -> bool | None:
    """Take an exclusive advisory lock on an open folder without waiting: True, False where
    another process holds it, None where this system or file system has no such locks."""
    if fcntl is None:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    except OSError:  # NFS refuses flock on a directory (EBADF); ENOLCK, EOPNOTSUPP
        return None
    return True


def _names(path: Path, fd: int) -> bool:
    """Whether `path` (not followed) is still the folder open as `fd`."""
    try:
        a, b = os.stat(path, follow_symlinks=False), os.fstat(fd)
    except FileNotFoundError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


def _build_folder(store: Path, entry_id: str) -> tuple[Path, int | None]:
    """A new folder for a build of `entry_id` to write in, and a descriptor of it holding its
    lock until closed (the kernel drops it when the process dies: a folder nobody locks has no
    writer left). Where locks are missing the folder is named .ID-XXXXXXXX, which a cleaner takes
    only once it has not changed for a day, and the descriptor is None."""
    for _ in range(8):  # another name each time a cleaner took the new folder before its lock
        path = Path(tempfile.mkdtemp(prefix=f".{entry_id}-", suffix=_BUILDING, dir=store))
        try:
            fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)
        except FileNotFoundError:
            continue
        locked = _lock(fd)
        if locked and _names(path, fd):
            return path, fd
        os.close(fd)
        if locked is None:
            with contextlib.suppress(OSError):
                path.rmdir()
            return Path(tempfile.mkdtemp(prefix=f".{entry_id}-", dir=store)), None
    raise OSError(errno.EAGAIN, f"no build folder for {entry_id} in {store} stayed ours long enough to lock it")


def _stale(path: Path, fd: int) -> bool:
    """Whether the build folder `path`, open as `fd`, has no writer left (see remove_stale_builds)."""
    if _BUILD_FOLDER.fullmatch(path.name):  # its lock tells; no locks here: nothing can tell
        return bool(_lock(fd)) and _names(path, fd)
    if _lock(fd) is False or not _names(path, fd):
        return False
    try:
        with os.scandir(fd) as listing:
            inside = {e.name: e.stat(follow_symlinks=False) for e in listing}
    except OSError:
        return False
    if not inside:  # nothing to reclaim, and nothing shows it was a build's
        return False
    if any(name not in (MANIFEST, MESH, WEIGHTS) or not stat.S_ISREG(st.st_mode) for name, st in inside.items()):
        return False  # a folder of the user's that happens to have such a name
    newest = max([os.fstat(fd).st_mtime, *(st.st_mtime for st in inside.values())])
    if time.time() - newest <= UNLOCKED_BUILD_AGE_S:
        return False
    cut_off = _cut_off(fd, set(inside))
    if cut_off is False:
        log.warning(
            "model store %s: kept %s: named like an older version's build folder, but it holds a complete entry "
            "(rename it if it is yours, remove it if not)",
            path.parent,
            path.name,
        )
    return bool(cut_off)


def _cut_off(fd: int, names: set[str]) -> bool | None:
    """Whether the entry's files `names`, in the folder open as `fd`, are a write that never
    finished, as write_entry leaves one killed or cut by a power loss: True with no manifest (it
    is written last), a manifest that is not JSON (cut short) or a file it lists missing or not
    matching its checksum; False for a complete entry (a user's copy as well as a build's);
    None where nothing can tell (an unreadable file, a manifest unlike any a build writes)."""
    if MANIFEST not in names:
        return True
    try:
        with _open_at(fd, MANIFEST) as f:
            raw = f.read(_MAX_MANIFEST + 1)
    except OSError:
        return None
    if len(raw) > _MAX_MANIFEST:
        return None
    try:
        manifest = json.loads(raw)
    except ValueError:  # not JSON, nor UTF-8
        return True
    files = manifest.get("files") if isinstance(manifest, dict) else None
    if not isinstance(files, dict) or set(files) != {MESH, WEIGHTS} or not all(map(_is_digest, files.values())):
        return None  # unlike any manifest a build writes: not a write cut off
    for fname, digest in files.items():
        if fname not in names:
            return True
        try:
            with _open_at(fd, fname) as f:
                if _digest(f) != digest:
                    return True
        except OSError:
            return None
    return False


def _is_digest(value: object) -> bool:
    """Whether a manifest's checksum is one a build writes: a SHA-256 hex digest."""
    return isinstance(value, str) and re.fullmatch(r"[0-9a-f]{64}", value) is not None


def _open_at(fd: int, name: str):
    """The regular file `name` in the folder open as `fd`, open for reading: never through a
    link, nor waiting on a FIFO put in its place."""
    f = os.open(name, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK, dir_fd=fd)
    if not stat.S_ISREG(os.fstat(f).st_mode):
        os.close(f)
        raise OSError(errno.EINVAL, f"{name} is not a regular file")
    return open(f, "rb")


def remove_stale_builds(store: Path) -> list[str]:
    """Remove the folders of builds whose process is gone (killed, or the machine lost power
    mid-write): a .ID-XXXXXXXX.build folder whose lock nobody holds; a live build's lock keeps
    its folder. A folder named .ID-XXXXXXXX (XXXXXXXX: tempfile's 8 characters of [a-z0-9_]) has
    no lock to tell (versions before the lock wrote it, and a build still does where the file
    system has no locks), and a user's backup may be named so (.liver-original, .liver-20240501):
    it is removed only when it is a real folder (not a link) that holds nothing but an entry's
    regular files, nothing in it has changed for UNLOCKED_BUILD_AGE_S (a day; a build fills its
    folder in seconds), and those files are shown to be a write cut off: no manifest, a manifest
    that is not JSON, or a file it lists missing or not matching its checksum. A complete entry
    under such a name is kept, with one warning naming it at each scan; an empty folder, or one
    holding anything else, is kept silently. Any other name (an aside entry, ..ID-*, a hidden
    folder of the user's) is never touched. One logged line per folder removed; returns their
    names. A store this process cannot write (a read-only mount, another owner's) keeps them,
    untouched: one warning says how many and how to clean them, and nothing fails."""
    store = Path(store)
    removed: list[str] = []
    try:
        names = sorted(
            p.name
            for p in store.iterdir()
            if _BUILD_FOLDER.fullmatch(p.name) or _UNLOCKED_BUILD_FOLDER.fullmatch(p.name)
        )
    except OSError:
        return removed
    writable = os.access(store, os.W_OK)  # else rmtree would empty a folder it cannot then remove
    left: list[str] = []
    for name in names:
        path = store / name
        try:  # never through a link: O_NOFOLLOW
            fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)
        except OSError:
            continue
        try:
            if not _stale(path, fd):
                continue
            if not writable:
                left.append(name)
                continue
            try:
                shutil.rmtree(path)
            except FileNotFoundError:  # a build removing the entry it swapped out, at the same time
                pass
            except OSError as exc:
                log.error("model store %s: cannot remove %s, a stale build's folder: %s", store, name, exc)
                continue
            what = "a build whose process is gone" if _BUILD_FOLDER.fullmatch(name) else "a build's write cut off"
            log.warning("model store %s: removed %s, the folder of %s", store, name, what)
            removed.append(name)
        finally:
            os.close(fd)
    if left:
        log.warning(
            "model store %s is read-only here: %d stale build folder(s) left (%s); remove them as a user who can "
            "write it, by hand once no build runs or by `elastreg serve` or a build into it",
            store,
            len(left),
            ", ".join(left[:3]) + (", ..." if len(left) > 3 else ""),
        )
    return removed


def _exchange(a: Path, b: Path) -> bool:
    """Swap two folders in one atomic step (Linux's renameat2 with RENAME_EXCHANGE); False where
    the system cannot, and nothing moved."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):  # not Linux, or a C library older than glibc 2.28
        return False
    at_fdcwd, rename_exchange = -100, 2
    return renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0


def _restore_aside(store: Path) -> None:
    """Put back an entry a build moved aside (..ID-XXXXXXXX) where the process died before its
    replacement went in: the store serves the old entry rather than none."""
    for path in store.iterdir():
        if not path.name.startswith(_ASIDE):
            continue
        entry_id = path.name[len(_ASIDE) :].rsplit("-", 1)[0]
        final = store / entry_id
        if path.is_dir() and not final.exists() and MODEL_ID.fullmatch(entry_id):
            try:
                os.replace(path, final)
                log.warning("model %s: restored the entry a build had moved aside (%s)", entry_id, path.name)
            except OSError as exc:
                log.error("model %s: cannot restore %s: %s", entry_id, path.name, exc)


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
    final = store / entry_id
    tmp, lock = _build_folder(store, entry_id)
    try:
        np.savez(tmp / MESH, nodes=mesh.nodes, tets=mesh.tets, fixed=mesh.fixed, region=np.asarray(region, np.int64))
        state = {k: v.detach().cpu().contiguous() for k, v in net.state_dict().items()}
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
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1, default=_jsonable))
        _share(tmp)  # before the rename: no moment where the served entry is private to its builder
        load_entry(tmp, name=entry_id)
        if not final.exists():
            os.replace(tmp, final)
        elif _exchange(tmp, final):  # one atomic step: no moment, crash or not, without the entry
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


def _regular_file(path: Path, folder: Path, name: str, fname: str) -> None:
    """A StoreError unless ``path`` is a regular file inside ``folder`` (no device, pipe or link
    out of the entry), checked without opening it."""
    try:
        inside = path.resolve().is_relative_to(folder.resolve())
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise StoreError(f"{name}: {fname} is missing") from None
    except OSError as exc:
        raise StoreError(f"{name}: {fname} cannot be read ({exc})") from None
    if not inside:
        raise StoreError(f"{name}: {fname} points outside the entry's folder")
    if not stat.S_ISREG(mode):
        raise StoreError(f"{name}: {fname} is not a regular file")


def _unreadable(name: str, fname: str, exc: OSError) -> StoreError:
    """The system would not let us read a file (permissions, I/O): named, in one line."""
    return StoreError(f"{name}: {fname} cannot be read ({exc.strerror or exc})")


def _one_line(text: str, limit: int = 300) -> str:
    """An exception's text as one log line (torch's and NumPy's messages span several)."""
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _check_manifest(manifest, name: str) -> None:
    """The manifest's shape and names, before any other file is opened."""
    if not isinstance(manifest, dict):
        raise StoreError(f"{name}: {MANIFEST} must hold a JSON object")
    version = manifest.get("format_version")
    if version != FORMAT_VERSION:
        raise StoreError(f"{name}: manifest format {version!r} is not supported (expected {FORMAT_VERSION})")
    files = manifest.get("files")
    if not isinstance(files, dict) or set(files) != {MESH, WEIGHTS}:
        listed = sorted(files)[:4] if isinstance(files, dict) else files
        raise StoreError(
            f"{name}: the manifest must list {MESH} and {WEIGHTS} under files, and nothing else "
            f"(it lists {listed!r:.200})"
        )
    if not all(_is_digest(d) for d in files.values()):
        raise StoreError(f"{name}: each file's checksum must be a SHA-256 hex digest")
    entry_id = manifest.get("id")
    if not isinstance(entry_id, str) or not MODEL_ID.fullmatch(entry_id):
        raise StoreError(f"{name}: the manifest's id must match {MODEL_ID.pattern}, got {entry_id!r:.80}")
    for key in ("mesh", "material", "network", "scene"):
        if not isinstance(manifest.get(key), dict):
            raise StoreError(f"{name}: the manifest has no {key!r} object")
    if not isinstance(manifest["scene"].get("material"), dict):
        raise StoreError(f"{name}: the manifest's scene has no 'material' object")
    material = manifest["material"]
    if not all(
        isinstance(material.get(k), (int, float)) and not isinstance(material.get(k), bool) for k in ("E", "nu")
    ):
        raise StoreError(f"{name}: the manifest's material needs numbers E and nu")
    if material.get("law", NeoHookean.law) != NeoHookean.law:
        raise StoreError(f"{name}: the manifest's material law {material['law']!r:.40} is not {NeoHookean.law!r}")
    try:
        NeoHookean.of(material)
    except ValueError as exc:
        raise StoreError(f"{name}: the manifest's material: {exc}") from None
    _check_twice(manifest, name)
    renumbered = manifest["mesh"].get("renumbered", False)
    if not isinstance(renumbered, bool):
        raise StoreError(f"{name}: the manifest's mesh.renumbered must be true or false, got {renumbered!r:.40}")
    _check_network(manifest["network"], name)


#: what a manifest records twice: a value the entry serves (or its data were drawn with) and
#: where the scene it was built from set it
_TWICE = (
    *((("material", k), ("scene", "material", k)) for k in ("law", "E", "nu")),
    (("training", "load_distribution", "steps"), ("scene", "training", "load_steps")),
    *(
        (("training", "load_distribution", k), ("scene", "training", k))
        for k in ("max_force", "seed", "multi_patch", "normal_fraction", "pull_fraction", "twist_fraction")
    ),
)
_ABSENT = object()


def _at(tree, path: tuple[str, ...]):
    for key in path:
        if not isinstance(tree, dict) or key not in tree:
            return _ABSENT
        tree = tree[key]
    return tree


def _check_twice(manifest: dict, name: str) -> None:
    """Each value the manifest records twice is the same both times: a material.E edited from
    4500 to 45000 was served at ten times the stiffness the network learnt, beside a scene that
    said 4500. A copy an older entry lacks is not compared."""
    for field, source in _TWICE:
        value, given = _at(manifest, field), _at(manifest, source)
        if value is _ABSENT or given is _ABSENT or value == given:  # 60 and 60.0 are one number
            continue
        raise StoreError(
            f"{name}: the manifest's {'.'.join(field)} {value!r:.40} is not the {given!r:.40} of the scene it was "
            f"built from ({'.'.join(source)}): changed after the build"
        )


def _whole(value, minimum: int = 1) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= minimum


def _check_network(spec: dict, name: str) -> None:
    """The manifest's network object: a layout this code builds, and whole numbers where the
    build reads them (a string "512" was read as the widths [5, 1, 2])."""
    layout = spec.get("layout")
    if layout not in ("reduced", "paper"):
        raise StoreError(f"{name}: the manifest's network layout {layout!r:.40} is not 'reduced' or 'paper'")
    keys = ("n_in", "n_out") if layout == "paper" else ("n_in",)
    for key in keys:
        if not _whole(spec.get(key)):
            raise StoreError(
                f"{name}: the manifest's network.{key} must be a whole number >= 1, got {spec.get(key)!r:.40}"
            )
    hidden = spec.get("hidden")
    if not (isinstance(hidden, list) and all(_whole(h) for h in hidden)):
        raise StoreError(
            f"{name}: the manifest's network.hidden must be a list of layer widths (whole numbers >= 1), "
            f"got {hidden!r:.40}"
        )
    if not _whole(spec.get("members", 1)):
        raise StoreError(
            f"{name}: the manifest's network.members must be a whole number >= 1, got {spec.get('members')!r:.40}"
        )


def _max_force(manifest: dict, name: str) -> float | None:
    """The scene's largest tool force (N; the error estimate's prior), None in an entry built
    before it was recorded; present, it must be a positive finite number."""
    training = manifest.get("training", {})
    spec = training.get("load_distribution", {}) if isinstance(training, dict) else None
    if not isinstance(spec, dict):
        raise StoreError(f"{name}: the manifest's training.load_distribution must be an object")
    value = spec.get("max_force")
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
        raise StoreError(f"{name}: the manifest's max_force must be a positive number of newtons, got {value!r:.40}")
    return float(value)


def _tool_patch(manifest: dict, name: str) -> int | None:
    """The most nodes one sampled load spread over (the scene's patch_nodes' upper end), None
    in an entry that records none; present, [low, high] whole numbers, 1 <= low <= high."""
    spec = manifest.get("training", {}).get("load_distribution", {})  # checked by _max_force
    value = spec.get("patch_nodes")
    if value is None:
        return None
    if not (
        isinstance(value, list) and len(value) == 2
        and all(isinstance(v, int) and not isinstance(v, bool) for v in value) and 1 <= value[0] <= value[1]
    ):  # fmt: skip
        raise StoreError(f"{name}: the manifest's patch_nodes must be [low, high] node counts, got {value!r:.40}")
    return int(value[1])


def _region(value: np.ndarray, n_nodes: int, name: str) -> np.ndarray:
    """The load region's node ids: distinct whole numbers in 0..n-1."""
    if value.ndim != 1 or value.dtype.kind not in "iu":
        raise StoreError(f"{name}: {MESH}'s region must be a list of node ids, got a {value.dtype} array {value.shape}")
    if value.size and (value.min() < 0 or value.max() >= n_nodes):
        raise StoreError(f"{name}: {MESH}'s region names nodes outside 0..{n_nodes - 1} (the mesh's)")
    if np.unique(value).size != value.size:
        raise StoreError(f"{name}: {MESH}'s region repeats node ids")
    return value.astype(np.int64)


def _check_fit(net: torch.nn.Module, mesh: TetMesh, region: np.ndarray, name: str) -> None:
    """The network answers for this mesh's nodes and reads this region's forces: a mesh.npz
    from another entry (under checksums made to match) loaded, and its first frame was a 500."""
    n3 = 3 * mesh.n_nodes
    shapes = {k: tuple(v.shape) for k, v in net.state_dict().items()}
    by_region = f"3 per node of the {region.size}-node region"
    if "basis" in shapes:  # the reduced layout: u = basis (3n, r) times the coefficients
        rows = {"basis": shapes["basis"][0]}
        n_in = shapes["skip.weight"][1]
        if "feature_basis" in shapes:  # the physics layout reads K0^-1 g in its features
            rows["feature_basis"] = shapes["feature_basis"][0]
            inputs, wanted = shapes["feature_basis"][1], "its feature_basis's columns"
        else:
            inputs, wanted = 3 * region.size, by_region
    else:  # the paper's: forces on the region in, displacements (3n) out
        layers = sorted((int(k.split(".")[1]), v) for k, v in shapes.items() if k.endswith(".weight") and len(v) == 2)
        rows = {"output": layers[-1][1][0]}
        n_in, inputs, wanted = layers[0][1][1], 3 * region.size, by_region
    for what, n in rows.items():
        if n != n3:
            raise StoreError(
                f"{name}: {MESH} does not fit {WEIGHTS}: the network's {what} has {n} rows (a {n // 3}-node "
                f"mesh's), the mesh has {mesh.n_nodes} nodes"
            )
    if n_in != inputs:
        raise StoreError(
            f"{name}: {MESH} does not fit {WEIGHTS}: the network reads {n_in} inputs, {wanted} would be {inputs}"
        )


def load_entry(path: Path, name: str | None = None) -> Entry:
    """Load and verify one entry; a :class:`StoreError` says what is wrong. `name`: the id it
    is to be served as (default: its folder's name)."""
    path = Path(path)
    name = path.name if name is None else name
    if not MODEL_ID.fullmatch(name):
        raise StoreError(f"{name!r:.80}: an entry's folder name must match {MODEL_ID.pattern}")
    _regular_file(path / MANIFEST, path, name, MANIFEST)
    if (path / MANIFEST).stat().st_size > _MAX_MANIFEST:
        raise StoreError(f"{name}: {MANIFEST} is over {_MAX_MANIFEST} bytes")
    try:
        manifest = json.loads((path / MANIFEST).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise StoreError(f"{name}: {MANIFEST} is not valid JSON ({exc})") from None
    except OSError as exc:
        raise _unreadable(name, MANIFEST, exc) from None
    _check_manifest(manifest, name)
    for fname in (MESH, WEIGHTS):  # every name checked before any file is read
        _regular_file(path / fname, path, name, fname)
    for fname, digest in manifest["files"].items():
        try:
            actual = sha256(path / fname)
        except OSError as exc:
            raise _unreadable(name, fname, exc) from None
        if actual != digest:
            raise StoreError(f"{name}: {fname} does not match its checksum in the manifest (corrupt or changed)")
    try:  # a zip of .npy arrays, read without pickle
        with np.load(path / MESH, allow_pickle=False) as z:
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
        state = load_file(str(path / WEIGHTS))
    except SafetensorError as exc:  # truncated, empty, another format under this name
        raise StoreError(f"{name}: {WEIGHTS} is not a readable safetensors file ({exc})") from None
    except OSError as exc:
        raise _unreadable(name, WEIGHTS, exc) from None
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

"""The data set on disk: one file per finished load path, written atomically (surrogate/data.py).

Per path file ``path_NNNNNN.npz``: ``forces`` (s, r, 3) float32 on the region nodes, ``u``
(s, n, 3) float32 for all nodes, ``newton_iterations`` (s,), s <= steps. A generation writes
them under `writing`, which removes the temporaries of writes killed mid-way first. A finished
file that is not what write_path wrote (cut short, emptied, arrays of other shapes) is set aside
as ``path_NNNNNN.npz.damaged`` with a warning, never deleted, and its path counts as not done.
``verified.txt`` names the files whose headers are known sound (written here, or checked once)
with their size and mtime then, so a resume opens only the others and those changed since.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import tempfile
import zipfile
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..folders import HAS_LOCKS, RANDOM, try_lock

log = logging.getLogger(__name__)

Array = np.ndarray

_PATH_NAME = re.compile(r"path_(\d{6})\.npz")
#: write_path's temporary, .path_NNNNNN-XXXXXXXX.tmp.npz (XXXXXXXX: tempfile's 8 characters)
_TEMPORARY = re.compile(rf"\.path_\d{{6}}-{RANDOM}\.tmp\.npz")
#: a path file's arrays, in write_path's order
_ARRAYS = ("forces", "u", "newton_iterations")
#: what reading a file that is not write_path's raises (a cut-short zip, an empty file, a bad
#: header, a missing array, a bad CRC); an OSError (EMFILE, EIO, a permission) says nothing of the
#: file's content, so it is never set aside for one: the error propagates
_DAMAGED = (zipfile.BadZipFile, EOFError, ValueError, KeyError, zlib.error)


#: the data folder's list of path files known sound, "name size mtime_ns" a line (appended to only)
VERIFIED = "verified.txt"


#: a finished path's file name (_PATH_NAME matches it)
_NAME = "path_{:06d}.npz"


def path_file(data_dir: Path, index: int) -> Path:
    return Path(data_dir) / _NAME.format(index)


def done_indices(data_dir: Path) -> set[int]:
    """Indices of finished paths (half-written files are hidden temporaries, never matched)."""
    names = (p.name for p in Path(data_dir).glob("path_*.npz"))
    return {int(m.group(1)) for m in map(_PATH_NAME.fullmatch, names) if m}


def write_path(data_dir: Path, result: dict) -> None:
    """Atomic write: a half-written file never looks like a finished path."""
    final = path_file(data_dir, result["index"])
    fd, name = tempfile.mkstemp(prefix=f".{final.stem}-", suffix=".tmp.npz", dir=final.parent)
    tmp = Path(name)  # a name of its own: two builds of one scene may write the same path
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, forces=result["forces"], u=result["u"], newton_iterations=result["newton_iterations"])
            f.flush()
            os.fsync(f.fileno())  # on disk before its name says finished: a power cut leaves no empty path file
            st = os.fstat(f.fileno())  # what VERIFIED records (a rename keeps size and mtime)
        os.replace(tmp, final)
        _sync_folder(final.parent)  # the rename itself on disk
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError) and exc.filename is None:  # written through the fd: it names no file
            raise OSError(exc.errno, exc.strerror, str(final)) from exc
        raise
    _add_verified(final.parent, [(result["index"], st)])  # whole on disk: no resume need open it


def _verified(data_dir: Path) -> dict[int, tuple[int, int]]:
    """Each index VERIFIED names -> its file's (size, mtime_ns) then, the last line's (a missing
    or unreadable list: none; a torn or foreign line: skipped)."""
    try:
        lines = (Path(data_dir) / VERIFIED).read_text(errors="replace").splitlines()
    except OSError:
        return {}
    known = {}
    for fields in map(str.split, lines):
        m = _PATH_NAME.fullmatch(fields[0]) if len(fields) == 3 else None
        if m and fields[1].isdigit() and fields[2].isdigit():
            known[int(m.group(1))] = (int(fields[1]), int(fields[2]))
    return known


def _add_verified(data_dir: Path, files: list[tuple[int, os.stat_result]]) -> None:
    """Append (index, stat) to VERIFIED in one write (O_APPEND: builds writing at once never tear
    each other's lines). Not synced: a line lost to a power cut costs a resume one header check."""
    if not files:
        return
    text = "".join(f"{path_file(data_dir, i).name} {st.st_size} {st.st_mtime_ns}\n" for i, st in files)
    with contextlib.suppress(OSError):  # a list that cannot be written: those files are checked again
        fd = os.open(Path(data_dir) / VERIFIED, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, text.encode())
        finally:
            os.close(fd)


def _sync_folder(folder: Path) -> None:
    """fsync a folder, so the renames in it survive a power cut (where the system can: not Windows)."""
    with contextlib.suppress(OSError):  # a folder that cannot be opened or synced: the rename stands
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _wrong_shapes(shapes: dict, region: int | None, nodes: int | None, steps: int | None) -> str | None:
    """Why arrays of these shapes are not a path's (forces (s, r, 3), u (s, n, 3), newton_iterations
    (s,), s <= steps), or None; a count given as None is not checked."""
    f, u, k = (tuple(shapes[name]) for name in _ARRAYS)
    if len(f) != 3 or len(u) != 3 or len(k) != 1 or f[2] != 3 or u[2] != 3 or not f[0] == u[0] == k[0]:
        return f"its arrays have shapes {f}, {u}, {k}, not (steps, region, 3), (steps, nodes, 3), (steps,)"
    for what, have, want in (("region nodes", f[1], region), ("nodes", u[1], nodes), ("steps", f[0], steps)):
        if want is not None and (have > want if what == "steps" else have != want):
            return f"it holds {have} {what}, not {'at most ' if what == 'steps' else ''}{want}"
    return None


def _header_shapes(path: Path) -> dict:
    """The shapes of a path file's arrays, from their headers alone (the data are not read)."""
    shapes = {}
    with zipfile.ZipFile(path) as z:
        for name in _ARRAYS:
            with z.open(f"{name}.npy") as f:
                version = np.lib.format.read_magic(f)
                read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
                shapes[name] = read(f)[0]
    return shapes


def _read_array(z: zipfile.ZipFile, name: str) -> Array:
    """One array of an open path file, read whole (the zip checks its CRC; no pickles)."""
    with z.open(f"{name}.npy") as f:
        return np.lib.format.read_array(f, allow_pickle=False)


def _set_aside(path: Path, why: str, then: str) -> None:
    """Rename a damaged path file to *.damaged (the user's data: never deleted), with one warning
    that ends with `then`: when its path is solved again."""
    aside, n = path.with_name(f"{path.name}.damaged"), 1
    while aside.exists():
        aside, n = path.with_name(f"{path.name}.{n}.damaged"), n + 1
    try:
        os.rename(path, aside)
    except FileNotFoundError:  # another build of this folder set it aside first
        return
    _sync_folder(path.parent)
    log.warning("%s is damaged (%s): set aside as %s; %s", path, why, aside.name, then)


def _damage(error: BaseException) -> str:
    return (str(error).splitlines() or [""])[0] or type(error).__name__


def intact_indices(data_dir: Path, indices: list[int], region: int, nodes: int, steps: int) -> list[int]:
    """The finished paths among `indices` whose files open and hold arrays of a path's shapes
    (their headers: no data read); the others are set aside (_set_aside) to be solved again.
    Only the files that VERIFIED does not name at their size and mtime are opened (every file
    cost a resume 150-300 us; a stat 3 us), and those found sound are added to it; the loader
    still reads every file whole."""
    known, kept, checked, folder = _verified(data_dir), [], [], os.fspath(data_dir)
    for i in indices:
        path = os.path.join(folder, _NAME.format(i))  # a str: a Path's making was most of a stat's cost
        try:
            st = os.stat(path)
            if known.get(i) == (st.st_size, st.st_mtime_ns):  # unchanged since it was known sound
                kept.append(i)
                continue
            why = _wrong_shapes(_header_shapes(Path(path)), region, nodes, steps)
        except FileNotFoundError:  # another build set it aside since it was listed: not done
            continue
        except _DAMAGED as exc:
            why = _damage(exc)
        if why is None:
            kept.append(i)
            checked.append((i, st))
        else:
            _set_aside(Path(path), why, "its load path counts as not done and is solved again")
    _add_verified(data_dir, checked)
    return kept


def load_dataset(
    data_dir: Path, indices: list[int] | None = None, region: int | None = None, nodes: int | None = None
) -> tuple[Array, Array, Array]:
    """All samples on disk: forces (N, r, 3), u (N, n, 3) float32, and each sample's path index.
    A file that cannot be read whole, or whose shapes are not a path's (`region` and `nodes`
    where given, else the first good file's), is set aside and left out: the next build solves
    its path again. A file gone since it was listed (another build set it aside) is skipped."""
    idx = sorted(done_indices(data_dir)) if indices is None else sorted(indices)
    F, U, P = [], [], []
    for i in idx:
        path = path_file(data_dir, i)
        try:
            with zipfile.ZipFile(path) as z:  # not np.load: a lone .npy under the name loads as an array
                arrays = {name: _read_array(z, name) for name in _ARRAYS}
            why = _wrong_shapes({k: a.shape for k, a in arrays.items()}, region, nodes, None)
        except FileNotFoundError:  # another build of this folder set it aside since it was listed
            continue
        except _DAMAGED as exc:
            why = _damage(exc)
        if why is not None:
            _set_aside(path, why, "left out of this build: the next solves its load path again")
            continue
        region, nodes = arrays["forces"].shape[1], arrays["u"].shape[1]  # the next files must agree
        F.append(arrays["forces"])
        U.append(arrays["u"])
        P.append(np.full(len(arrays["forces"]), i))
    if not F:
        raise FileNotFoundError(f"no samples in {data_dir}")
    return np.concatenate(F), np.concatenate(U), np.concatenate(P)


@contextlib.contextmanager
def writing(data_dir: Path) -> Iterator[None]:
    """The data folder held while a generation writes paths to it: a shared lock on the folder
    (builds of one scene share it and may write at once; the kernel drops it with the process).
    First, where no other process holds it, the temporaries of writes killed mid-way (write_path's,
    nothing else) are removed: with another build writing, one may be its path in flight."""
    if not HAS_LOCKS:  # Windows: no folder to hold, so no temporary is ever taken for a leftover
        yield
        return
    fd = os.open(data_dir, os.O_RDONLY | os.O_DIRECTORY)
    try:
        if try_lock(fd):  # None where there are no locks: nothing is taken for a leftover
            _remove_temporaries(Path(data_dir))
        try_lock(fd, shared=True, wait=True)  # waits only for another's clean-up; this build writes nothing yet
        yield
    finally:
        os.close(fd)


def _remove_temporaries(data_dir: Path) -> None:
    """Remove the temporaries in `data_dir` that write_path left when killed mid-write."""
    left = [p for p in data_dir.glob(".path_*.tmp.npz") if _TEMPORARY.fullmatch(p.name)]
    for path in left:
        path.unlink(missing_ok=True)
    if left:
        log.info("%s: removed %d half-written path files of a build killed mid-write", data_dir, len(left))

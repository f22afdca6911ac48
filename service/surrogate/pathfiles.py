"""The data set on disk: one file per finished load path, written atomically (surrogate/data.py).

Per path file ``path_NNNNNN.npz``: ``forces`` (s, r, 3) float32 on the region nodes, ``u``
(s, n, 3) float32 for all nodes, ``newton_iterations`` (s,), s <= steps. A generation writes
them under `writing`, which removes the temporaries of writes killed mid-way first.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..folders import HAS_LOCKS, RANDOM, try_lock

log = logging.getLogger(__name__)

Array = np.ndarray

_PATH_NAME = re.compile(r"path_(\d{6})\.npz")
#: write_path's temporary, .path_NNNNNN-XXXXXXXX.tmp.npz (XXXXXXXX: tempfile's 8 characters)
_TEMPORARY = re.compile(rf"\.path_\d{{6}}-{RANDOM}\.tmp\.npz")


def path_file(data_dir: Path, index: int) -> Path:
    return Path(data_dir) / f"path_{index:06d}.npz"


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
        os.replace(tmp, final)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError) and exc.filename is None:  # written through the fd: it names no file
            raise OSError(exc.errno, exc.strerror, str(final)) from exc
        raise


def load_dataset(data_dir: Path, indices: list[int] | None = None) -> tuple[Array, Array, Array]:
    """All samples on disk: forces (N, r, 3), u (N, n, 3) float32, and each sample's path index."""
    idx = sorted(done_indices(data_dir)) if indices is None else sorted(indices)
    F, U, P = [], [], []
    for i in idx:
        with np.load(path_file(data_dir, i)) as z:
            F.append(z["forces"])
            U.append(z["u"])
            P.append(np.full(len(z["forces"]), i))
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

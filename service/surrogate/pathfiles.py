"""The data set on disk: one file per finished load path, written atomically (surrogate/data.py).

Per path file ``path_NNNNNN.npz``: ``forces`` (s, r, 3) float32 on the region nodes, ``u``
(s, n, 3) float32 for all nodes, ``newton_iterations`` (s,), s <= steps.
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path

import numpy as np

Array = np.ndarray

_PATH_NAME = re.compile(r"path_(\d{6})\.npz")


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

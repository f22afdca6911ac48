"""An entry's files: their names, the manifest's format, their checksums, and the error that
says what is wrong with an entry."""

from __future__ import annotations

import hashlib
import logging
import re
from pathlib import Path

#: one logger for the whole store (service.store), whichever of its modules logs
log = logging.getLogger(__package__)

FORMAT_VERSION = 1
MANIFEST = "manifest.json"
MESH = "mesh.npz"
WEIGHTS = "weights.safetensors"
_MAX_MANIFEST = 1 << 20  # bytes
#: the largest mesh or weights file an entry may hold: the loader reads each whole into memory
#: (a 100k-node organ's reduced ensemble is a few hundred MB; a sparse 8 GiB file is refused unread)
MAX_DATA_FILE = 4 << 30  # bytes


class StoreError(RuntimeError):
    """An entry that cannot be used, and why."""


def sha256(path: Path) -> str:
    with open(path, "rb") as f:
        return _digest(f)


def sha256_of(data: bytes) -> str:
    """The SHA-256 of bytes already read (the loader checks the very bytes it then serves)."""
    return hashlib.sha256(data).hexdigest()


def _digest(f) -> str:
    """The SHA-256 of an open binary file, read from where it stands to its end."""
    h = hashlib.sha256()
    for chunk in iter(lambda: f.read(1 << 20), b""):
        h.update(chunk)
    return h.hexdigest()


def _is_digest(value: object) -> bool:
    """Whether a manifest's checksum is one a build writes: a SHA-256 hex digest."""
    return isinstance(value, str) and re.fullmatch(r"[0-9a-f]{64}", value) is not None

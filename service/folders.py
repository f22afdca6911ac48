"""Folders held and swapped: advisory locks on open folders, a new folder made and locked, two
folders swapped in one step, and the random part of tempfile's names.

A build's folder, a data folder being written and a bench run's scratch folder are each held by
a flock on the folder itself: the kernel drops it when the process dies, so a folder nobody
holds has no writer left. Where the system or the file system has no such locks (Windows; NFS
refuses flock on a folder), :func:`try_lock` says so and the callers take nothing for stale. A
store's entry and a bench report go in place by :func:`exchange` where the system has it.
"""

from __future__ import annotations

import ctypes
import errno
import functools
import os
import tempfile
from pathlib import Path

try:  # advisory locks: POSIX systems
    import fcntl
except ImportError:  # pragma: no cover - Windows: callers hold nothing and take nothing for stale
    fcntl = None  # type: ignore[assignment]

#: whether this system has the locks at all
HAS_LOCKS = fcntl is not None
#: tempfile.mkstemp's and mkdtemp's 8 random characters, as a regular expression
RANDOM = "[a-z0-9_]{8}"
#: renameat2's flag that swaps two names in one step (linux/fs.h), and its "relative to the cwd"
_RENAME_EXCHANGE, _AT_FDCWD = 2, -100


def try_lock(fd: int, shared: bool = False, wait: bool = False) -> bool | None:
    """Lock the open file or folder `fd` (exclusive, or `shared`), waiting only if `wait`: True,
    False where another process holds a conflicting lock, None where this system or file system
    has no such locks."""
    if fcntl is None:
        return None
    how = (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | (0 if wait else fcntl.LOCK_NB)
    try:
        fcntl.flock(fd, how)
    except BlockingIOError:
        return False
    except OSError:  # NFS refuses flock on a directory (EBADF); ENOLCK, EOPNOTSUPP
        return None
    return True


def same_folder(path: Path, fd: int) -> bool:
    """Whether `path` (not followed) is still the folder open as `fd`."""
    try:
        a, b = os.stat(path, follow_symlinks=False), os.fstat(fd)
    except FileNotFoundError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


def locked_folder(parent: Path, prefix: str, suffix: str = "") -> tuple[Path, int, bool | None]:
    """A new folder in `parent` named `prefix`, 8 random characters and `suffix`, open: (path,
    fd, True) locked, or (path, fd, None) where there are no locks. OSError where a cleaner took
    every new folder before its lock (another name each time, 8 tries)."""
    for _ in range(8):
        path = Path(tempfile.mkdtemp(prefix=prefix, suffix=suffix, dir=parent))
        try:
            fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)
        except FileNotFoundError:
            continue
        locked = try_lock(fd)
        if locked is None or (locked and same_folder(path, fd)):
            return path, fd, locked
        os.close(fd)
    raise OSError(errno.EAGAIN, f"no new folder {prefix}* in {parent} stayed this process's long enough to lock it")


@functools.cache
def _renameat2():
    """The C library's renameat2: glibc 2.28 on; None elsewhere (macOS, musl before 1.2.x, Windows)."""
    try:
        return ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError, TypeError):
        return None


def exchange(a: Path, b: Path) -> bool:
    """Swap the names `a` and `b` in one atomic step; False where the system or file system
    cannot, and nothing moved; OSError for any other failure (EBUSY: a mount point; EXDEV)."""
    renameat2 = _renameat2()
    if renameat2 is None:
        return False
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))

"""Advisory locks on open folders, and the random part of tempfile's names.

A build's folder, a data folder being written and a bench run's scratch folder are each held by
a flock on the folder itself: the kernel drops it when the process dies, so a folder nobody
holds has no writer left. Where the system or the file system has no such locks (Windows; NFS
refuses flock on a folder), :func:`try_lock` says so and the callers take nothing for stale.
"""

from __future__ import annotations

try:  # advisory locks: POSIX systems
    import fcntl
except ImportError:  # pragma: no cover - Windows: callers hold nothing and take nothing for stale
    fcntl = None  # type: ignore[assignment]

#: whether this system has the locks at all
HAS_LOCKS = fcntl is not None
#: tempfile.mkstemp's and mkdtemp's 8 random characters, as a regular expression
RANDOM = "[a-z0-9_]{8}"


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

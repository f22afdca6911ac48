"""Compiled kernels where numba imports, so that a module can keep its NumPy path beside them.

numba compiles on first use and caches the machine code on disk (numba is a dependency; the
fallback keeps a kernel's caller working where it cannot be imported).
"""

from __future__ import annotations

import functools
from typing import Callable


def compiled(fn: Callable) -> Callable[[], Callable | None]:
    """A cached getter of `fn` compiled by numba (nopython, no GIL), or of None without numba."""

    @functools.cache
    def get():
        try:
            import numba
        except ImportError:  # pragma: no cover - numba is a dependency
            return None
        return numba.njit(cache=True, nogil=True)(fn)

    return get

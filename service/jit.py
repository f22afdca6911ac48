"""Compiled kernels: the tree's one way to use numba.

A kernel module holds plain Python functions (readable, and where there is one, beside the NumPy
path they must agree with) and names what numba should compile at its end::

    compiled = kernels(energy, internal_force, helpers=(_deformation,))
    ...
    K = compiled()            # a namespace of compiled kernels, or None where numba is missing
    K.energy(u, tets, ...)

Importing a kernel module imports no numba and compiles nothing. The first call of the getter
imports numba, compiles each helper (inlined, in order: a helper may call the ones before it),
binds the compiled helpers into the kernels' globals and wraps the kernels; each compiles on
its first call, or at once for a kernel given with a signature (``(fn, "void(f8[::1])")``), so
that a caller can pay the compile when a session opens rather than in its first frame. Every
kernel is ``njit(cache=True, nogil=True)``: machine code cached on disk, and the GIL released,
so that solves on the server's threads run side by side.
"""

from __future__ import annotations

import functools
import logging
import types
from collections.abc import Callable

log = logging.getLogger(__name__)

Kernel = Callable | tuple[Callable, str]  # a function, or a function and its one signature


def available() -> bool:
    """Whether numba imports (the compiled kernels can be used)."""
    return _numba() is not None


def kernels(*functions: Kernel, helpers: tuple[Callable, ...] = ()) -> Callable[[], types.SimpleNamespace | None]:
    """A cached getter of `functions` compiled by numba, by name, or of None without numba."""

    @functools.cache
    def get() -> types.SimpleNamespace | None:
        numba = _numba()
        if numba is None:
            return None
        jit = functools.partial(numba.njit, cache=True, nogil=True)
        scope: dict = {}
        for helper in helpers:  # in order: a helper may call the ones before it
            scope[helper.__name__] = jit(inline="always")(_rebind(helper, scope))
        compiled, module = {}, ""
        for item in functions:
            fn, signature = item if isinstance(item, tuple) else (item, None)
            source = _rebind(fn, scope) if scope else fn
            compiled[fn.__name__] = (jit(signature) if signature else jit)(source)
            module = fn.__module__
        log.debug("numba %s: %s from %s", numba.__version__, ", ".join(compiled), module)
        return types.SimpleNamespace(**compiled)

    return get


@functools.cache
def _numba():
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is a dependency; the NumPy paths remain
        return None
    return numba


def _rebind(source: Callable, helpers: dict) -> Callable:
    """``source`` with the named globals bound to ``helpers``, for numba to compile.

    numba resolves a kernel's globals when it compiles it, and calls compiled functions only;
    binding the compiled helpers here, rather than decorating at import, keeps numba an import
    of first use and the plain functions plain. The code object is the source's own, so
    numba's disk cache (keyed on the file and the function's name) still finds it.
    """
    scope = dict(source.__globals__, **helpers)
    fn = types.FunctionType(source.__code__, scope, source.__name__, source.__defaults__)
    fn.__module__, fn.__qualname__, fn.__doc__ = (
        source.__module__,
        source.__qualname__,
        source.__doc__,
    )
    return fn

"""Sparse direct factorisation of symmetric stiffness matrices, behind one small interface.

Every Newton step factorises a matrix whose sparsity never changes, so a :class:`SparseSolver`
is made once per pattern (symbolic analysis, ordering) and then refactorised numerically as
often as needed. Backends, fastest first (measured on the paper's liver, 8,823 dofs, 2 cores;
``python -m service.bench.solvers`` prints the current figures):

- ``pardiso``: Intel MKL PARDISO through ctypes (the ``mkl`` wheel), SPD mode, upper triangle;
  about 15 ms a numeric factorisation, 1-2 ms a solve.
- ``cholmod``: CHOLMOD through scikit-sparse, when installed (needs SuiteSparse headers).
- ``superlu``: SciPy's SuperLU, always available; about 15x slower on the liver.

A factorisation reports whether the matrix was positive definite, so the Newton solver can
shift an indefinite tangent instead of following a non-descent direction.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import threading
from collections.abc import Iterator
from functools import lru_cache
from typing import Protocol

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..spare import helping
from ..sparse_libs import missing
from ..sparse_libs import mkl as _mkl

log = logging.getLogger(__name__)

Array = np.ndarray

#: PARDISO's threads for the factorisations a frame makes while a core is spare (spare.helping):
#: the liver's tangent in 11.5 against 20.4 ms (docs/performance.md)
FACTOR_THREADS = 2


class NotPositiveDefinite(ArithmeticError):
    """The matrix handed to a Cholesky-type factorisation was not positive definite."""


class SparseSolver(Protocol):
    """Factorise matrices of one fixed sparsity pattern, then solve with the latest factor."""

    name: str

    def factor(self, K: sp.csr_matrix) -> None:
        """Factorise K (symmetric, full storage). Raises NotPositiveDefinite if it is not SPD."""

    def solve(self, b: Array) -> Array:
        """K^{-1} b for the last matrix factorised. Shape: (N,) or (N, r)."""


# -- SuperLU (always there) ------------------------------------------------------------------


class SuperLUSolver:
    """SciPy SuperLU with a symmetric-mode ordering; a negative pivot flags an indefinite K."""

    name = "superlu"

    def __init__(self, pattern: sp.csr_matrix, single: bool = False) -> None:
        self._lu = None
        self._dtype = np.float32 if single else np.float64

    def factor(self, K: sp.csr_matrix) -> None:
        lu = spla.splu(
            sp.csc_matrix(K, dtype=self._dtype),
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )
        # with diagonal pivoting on a symmetric matrix, U's diagonal has the signs of the
        # LDL^T pivots: all positive iff K is positive definite
        if (lu.U.diagonal() <= 0).any():
            raise NotPositiveDefinite("SuperLU found a non-positive pivot")
        self._lu = lu

    def solve(self, b: Array) -> Array:
        return self._lu.solve(np.asarray(b, self._dtype)).astype(np.float64, copy=False)


# -- CHOLMOD (optional, scikit-sparse) -------------------------------------------------------


class CholmodSolver:
    """CHOLMOD supernodal Cholesky; the symbolic analysis is shared by all refactorisations."""

    name = "cholmod"

    def __init__(self, pattern: sp.csr_matrix, single: bool = False) -> None:
        from sksparse import cholmod  # optional dependency: fails here, not at import (double only)

        self._cholmod = cholmod
        self._symbolic = cholmod.analyze(sp.csc_matrix(pattern), mode="supernodal")
        self._factor = None

    def factor(self, K: sp.csr_matrix) -> None:
        try:
            self._factor = self._symbolic.cholesky(sp.csc_matrix(K))
        except self._cholmod.CholmodNotPositiveDefiniteError as exc:
            raise NotPositiveDefinite(str(exc)) from exc

    def solve(self, b: Array) -> Array:
        return self._factor(np.asarray(b, np.float64))


# -- PARDISO (MKL through ctypes) ------------------------------------------------------------


@lru_cache(maxsize=1)
def _mkl_pardiso():
    """The MKL ``pardiso`` entry point, or None where MKL is not installed."""
    lib = _mkl()
    if lib is not None:
        fn = lib.pardiso
        i32p = ctypes.POINTER(ctypes.c_int32)
        fn.argtypes = (
            [ctypes.POINTER(ctypes.c_int64)]
            + [i32p] * 5
            + [ctypes.c_void_p]
            + [i32p] * 6
            + [ctypes.c_void_p, ctypes.c_void_p, i32p]
        )
        fn.restype = None
        return fn
    return None


@contextlib.contextmanager
def _mkl_threads(n: int) -> Iterator[None]:
    """MKL's threads for the calling thread's calls within the block. Thread-local
    (MKL_Set_Num_Threads_Local), so other threads' solves keep one each; the process-wide
    setters do not reach a thread whose local count is set (threadpoolctl sets it)."""
    setter = getattr(_mkl(), "MKL_Set_Num_Threads_Local", None) if n > 1 else None
    if setter is None:  # one thread (every solver but a frame's second): nothing to look up
        yield
        return
    before = setter(n)
    try:
        yield
    finally:
        setter(before)  # 0, none set before: back to the process-wide count


def _i32(v: int):
    return ctypes.byref(ctypes.c_int32(v))


class PardisoSolver:
    """MKL PARDISO in real-SPD mode (mtype 2) on the upper triangle, zero-based indices.

    Phase 11 (ordering and symbolic factorisation) runs once per pattern; each :meth:`factor`
    runs phase 22 only. One instance holds one factor and is not shared between threads.
    `single`: factor and solve in float32 (iparm 28), about half a solve's time (memory-bound)
    at a relative error near 1e-5 on the liver: for solves that only estimate. `threads`: MKL's
    threads for every call, fixed at the analysis (:class:`SpareCoreSolver` holds two).
    """

    name = "pardiso"
    _MTYPE = 2  # real symmetric positive definite

    def __init__(self, pattern: sp.csr_matrix, single: bool = False, threads: int = 1) -> None:
        self.threads = threads
        fn = _mkl_pardiso()
        if fn is None:
            raise RuntimeError(missing("pardiso"))
        self._fn = fn
        upper = sp.triu(sp.csr_matrix(pattern), format="csr")
        upper.sort_indices()
        self.n = upper.shape[0]
        self._ia = upper.indptr.astype(np.int32)
        self._ja = upper.indices.astype(np.int32)
        # where each upper-triangle entry sits in the full CSR data of the same pattern
        full = sp.csr_matrix(pattern, copy=True)
        full.sort_indices()
        full.data = np.arange(full.nnz, dtype=np.float64)
        self._take = sp.triu(full, format="csr").data.astype(np.int64)
        self._full_indptr = full.indptr.copy()
        self._full_indices = full.indices.copy()
        self._dtype = np.float32 if single else np.float64
        self._data = np.zeros(self._ja.size, self._dtype)
        self._pt = np.zeros(64, np.int64)
        self._iparm = np.zeros(64, np.int32)
        self._iparm[0] = 1  # we set the parameters below
        self._iparm[1] = 0  # minimum degree ordering (fastest numeric phase here)
        self._iparm[9] = 13  # pivot perturbation 1e-13
        self._iparm[27] = int(single)  # precision of the matrix, the factor and the vectors
        self._iparm[34] = 1  # zero-based indices
        self._lock = threading.Lock()
        self._factored = False
        self._call(11, np.zeros(self.n))

    def _call(self, phase: int, b: Array) -> Array:
        with _mkl_threads(self.threads):  # every phase on the analysis's count: a factor on fewer crashed
            return self._phase(phase, b)

    def _phase(self, phase: int, b: Array) -> Array:
        b = np.asfortranarray(b, dtype=self._dtype)
        x = np.zeros_like(b)
        err = ctypes.c_int32(0)
        nrhs = 1 if b.ndim == 1 else b.shape[1]
        self._fn(
            self._pt.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)),
            _i32(1), _i32(1), _i32(self._MTYPE), _i32(phase), _i32(self.n),
            self._data.ctypes.data,
            self._ia.ctypes.data_as(ctypes.POINTER(ctypes.c_int32)),
            self._ja.ctypes.data_as(ctypes.POINTER(ctypes.c_int32)),
            None, _i32(nrhs),
            self._iparm.ctypes.data_as(ctypes.POINTER(ctypes.c_int32)),
            _i32(0), b.ctypes.data, x.ctypes.data, ctypes.byref(err),
        )  # fmt: skip
        if err.value == -4:
            raise NotPositiveDefinite("PARDISO: zero or negative pivot (matrix not SPD)")
        if err.value != 0:
            raise ArithmeticError(f"PARDISO phase {phase} failed with error {err.value}")
        return np.ascontiguousarray(x)

    def factor(self, K: sp.csr_matrix) -> None:
        if not (np.array_equal(K.indptr, self._full_indptr) and np.array_equal(K.indices, self._full_indices)):
            raise ValueError("matrix does not have the sparsity pattern this solver analysed")
        with self._lock:
            self._data[:] = K.data[self._take]
            self._factored = False
            self._call(22, np.zeros(self.n))
            self._factored = True

    def solve(self, b: Array) -> Array:
        with self._lock:
            if not self._factored:
                raise RuntimeError("solve() before a successful factor()")
            return self._call(33, b).astype(np.float64, copy=False)

    def __del__(self) -> None:
        try:
            if self._pt.any():
                self._call(-1, np.zeros(self.n))
        except Exception:  # interpreter shutdown: nothing left to free into
            pass


class SpareCoreSolver:
    """Two PARDISO solvers of one pattern: one on a single thread, and one on FACTOR_THREADS for
    the factorisations a frame makes while a core is spare (spare.helping). PARDISO must
    factorise on the thread count it analysed with (fewer crashed it), so the count picks the
    solver, not the call. Solves go to the one holding the latest factor."""

    name = "pardiso"

    def __init__(self, pattern: sp.csr_matrix, single: bool = False) -> None:
        self._pattern, self._single = pattern, single
        self._one = self._current = PardisoSolver(pattern, single)
        self._more: PardisoSolver | None = None  # analysed on first use

    def factor(self, K: sp.csr_matrix) -> None:
        solver = self._one
        if helping():
            if self._more is None:
                self._more = PardisoSolver(self._pattern, self._single, threads=FACTOR_THREADS)
            solver = self._more
        self._current = solver  # a failed factor leaves it refusing solves, as a lone solver does
        solver.factor(K)

    def solve(self, b: Array) -> Array:
        return self._current.solve(b)


BACKENDS = {"pardiso": PardisoSolver, "cholmod": CholmodSolver, "superlu": SuperLUSolver}


def available_backends() -> list[str]:
    """Backends that load on this machine, fastest first."""
    return [name for name in BACKENDS if missing(name) is None]  # BACKENDS lists them fastest first


def make_solver(
    pattern: sp.csr_matrix, backend: str | None = None, single: bool = False, spare_core: bool = False
) -> SparseSolver:
    """A solver for matrices with this sparsity: the named backend, or the fastest available.

    `backend` may also come from the environment variable ELASTREG_SOLVER. `single`: factor in
    float32 where the backend can (PARDISO, SuperLU; CHOLMOD stays double); solutions come
    back in float64 either way. `spare_core`: PARDISO factorises on two threads where a frame
    has a core to spare (:class:`SpareCoreSolver`; a Newton method's solver).
    """
    backend = backend or os.environ.get("ELASTREG_SOLVER") or available_backends()[0]
    if backend not in BACKENDS:
        raise ValueError(f"unknown solver backend {backend!r}; choose from {sorted(BACKENDS)}")
    if spare_core and backend == "pardiso":
        return SpareCoreSolver(pattern, single)
    return BACKENDS[backend](pattern, single)


def refined_solve(K, approx_solve, b: Array, rtol: float = 1e-10, max_steps: int = 6) -> Array:
    """Solve K x = b by iterative refinement on a nearby factorisation (approx_solve ~ K^-1)."""
    x = approx_solve(b)
    bn = np.linalg.norm(b) or 1.0
    for _ in range(max_steps):
        r = b - K @ x
        if np.linalg.norm(r) <= rtol * bn:
            break
        x = x + approx_solve(r)
    return x

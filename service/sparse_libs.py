"""The native libraries behind the optional sparse factorisations, and whether they load here.

One probe each, shared by the FEM's solvers (``service/fem/linsolve.py``) and the start-up check
of ``ELASTREG_SOLVER`` (``service/config.py``, a layer below the FEM): the check refuses exactly
what the solvers would fail to load.
"""

from __future__ import annotations

import ctypes
import glob
import logging
import os
import site
import sys
from functools import lru_cache

log = logging.getLogger(__name__)


@lru_cache(maxsize=1)
def mkl() -> ctypes.CDLL | None:
    """MKL's runtime library (``ELASTREG_MKL_RT``, else the ``mkl`` wheel's), or None where MKL
    is not installed."""
    candidates = [os.environ.get("ELASTREG_MKL_RT", "")]
    for prefix in (sys.prefix, site.getuserbase(), *site.getsitepackages()):
        candidates += sorted(glob.glob(os.path.join(prefix, "[Ll]ib*", "**", "*mkl_rt*"), recursive=True), key=len)
    for path in candidates:
        if not path:
            continue
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        log.debug("MKL from %s", path)
        if hasattr(lib, "MKL_Set_Num_Threads_Local"):
            lib.MKL_Set_Num_Threads_Local.restype = ctypes.c_int
        return lib
    return None


def missing(backend: str) -> str | None:
    """Why the factorisation `backend` cannot load on this machine, naming what to install;
    None where it can (superlu, SciPy's, always can)."""
    if backend == "pardiso" and mkl() is None:
        return (
            "pardiso needs Intel MKL's runtime library (mkl_rt), which is not installed: "
            "pip install mkl (x86_64 only), or point ELASTREG_MKL_RT at an mkl_rt library"
        )
    if backend == "cholmod":
        try:
            import sksparse.cholmod  # noqa: F401
        except ImportError as exc:
            return f"cholmod needs scikit-sparse, which does not load ({exc}): pip install 'elastreg[cholmod]'"
    return None

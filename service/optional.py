"""Optional dependencies, imported at first use with an error that names the extra to install.

The server (the base install) needs none of them: the trainer needs ``[train]`` (dask, tqdm,
tetgen), the benchmarks ``[bench]`` (matplotlib, psutil), the client ``[client]``.
"""

from __future__ import annotations

import importlib
from types import ModuleType

#: the extra that installs each optional top-level package
EXTRAS = {
    "dask": "train",
    "distributed": "train",
    "tqdm": "train",
    "tetgen": "train",
    "matplotlib": "bench",
    "psutil": "bench",
    "httpx": "client",
    "websockets": "client",
}


class MissingDependency(ImportError):
    """An optional package is not installed; the message says which extra brings it."""


def need(module: str, purpose: str) -> ModuleType:
    """Import ``module`` (dotted names too) or raise MissingDependency naming the extra."""
    try:
        return importlib.import_module(module)
    except ImportError as err:
        top = module.partition(".")[0]
        extra = EXTRAS.get(top, "test")
        raise MissingDependency(
            f"{purpose} needs the {top!r} package, which is not installed: pip install 'elastreg[{extra}]'"
        ) from err

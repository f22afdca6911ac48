"""What a benchmark ran on: CPU, cores, GPU, library versions and the commit, for the report."""

from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path


def _cpu_model() -> str:
    """The CPU's name, with its family, model and cache per core: a VM may name only the
    vendor's line ("AMD EPYC"), which hides generations that differ by 2x in these benchmarks
    (a Zen 3 against a Zen 5 EPYC, both named so)."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        # the last processor's fields win: all processors of a machine are alike
        info = {k.strip(): v.strip() for k, _, v in (line.partition(":") for line in lines) if v}
    except OSError:
        info = {}
    name = info.get("model name")
    if not name:
        return platform.processor() or platform.machine()
    facts = [f"family {info['cpu family']}, model {info['model']}" if "cpu family" in info and "model" in info else "",
             f"cache {info['cache size']}" if "cache size" in info else ""]  # fmt: skip
    facts = [f for f in facts if f]
    return f"{name} ({'; '.join(facts)})" if facts else name


def _commit() -> str:
    root = Path(__file__).resolve().parents[2]
    try:
        sha = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=5
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=5,
        ).stdout.strip()
        return sha + ("+local changes" if dirty else "") if sha else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def describe() -> dict:
    import numpy
    import scipy
    import torch

    from .. import __version__
    from ..fem.linsolve import available_backends

    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {
        "cpu": _cpu_model(),
        "cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "gpu": gpu,
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "torch": torch.__version__,
        "sparse_solver": available_backends()[0],
        "elastreg": __version__,
        "commit": _commit(),
    }

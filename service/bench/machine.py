"""What a benchmark ran on: CPU, cores, GPU, library versions and the commit, for the report."""

from __future__ import annotations

import contextlib
import hashlib
import os
import platform
import subprocess
from pathlib import Path

from .swap import SCRATCH_PREFIX


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


#: the checkout this code runs from, whose commit a report names
ROOT = Path(__file__).resolve().parents[2]


def _git(root: Path, *args: str) -> bytes:
    return subprocess.run(["git", "-C", str(root), *args], capture_output=True, timeout=10, check=True).stdout


def _commit(root: Path = ROOT) -> str:
    """HEAD's short hash, and where the tree differs from it "+local changes" with a short hash
    of the changes (the diff against HEAD and the untracked files, not ignored ones, with their
    contents): untracked code ran unseen, and two different dirty trees stamped alike, so
    ``--resume`` took rows of one for the other. A report run's own scratch files (its lock,
    its staging folder: swap.SCRATCH_PREFIX) are not the code: its lock, made before its
    first stamp, marked every bench run in reports/ dirty."""
    try:
        sha = _git(root, "rev-parse", "--short", "HEAD").decode().strip()
        if not sha:
            return "unknown"
        digest = hashlib.sha256(_git(root, "diff", "HEAD", "--binary", "--no-ext-diff"))
        listed = _git(root, "ls-files", "--others", "--exclude-standard", "-z").split(b"\0")
        scratch = os.fsencode(SCRATCH_PREFIX)
        untracked = [n for n in listed if n and not any(p.startswith(scratch) for p in n.split(b"/"))]
        for name in sorted(untracked):
            digest.update(b"\0" + name + b"\0")
            with contextlib.suppress(OSError):  # gone or unreadable: its name alone
                digest.update((root / os.fsdecode(name)).read_bytes())
        dirty = digest.hexdigest() != hashlib.sha256(b"").hexdigest()
        return f"{sha}+local changes {digest.hexdigest()[:8]}" if dirty else sha
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def cores() -> int:
    """The cores this process may run on (its affinity where the system tells it)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def describe() -> dict:
    import numpy
    import scipy
    import torch

    from .. import __version__
    from ..fem.linsolve import available_backends

    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {
        "cpu": _cpu_model(),
        "cores": cores(),
        "gpu": gpu,
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "torch": torch.__version__,
        "sparse_solver": available_backends()[0],
        "elastreg": __version__,
        "commit": _commit(),
    }

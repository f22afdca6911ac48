"""A timed build's one-off loads, paid before it plans its minutes: a tiny build end to end.

A cold process pays, once, numba's kernels (compiled or read from its cache), MKL's runtime and
the factorisation's set-up, torch's first forward and backward (its optimiser imports
torch._dynamo: 2.5 s under load) and the store's first write and load-back. Paid inside the
data or the training they ran past the share that had been planned without them (a cold
`elastreg train --minutes` overran by up to 19 s under a load of 16); paid here, the plan uses
what is left, and the write's reserve is this machine's write, measured.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import time
from pathlib import Path

import numpy as np

from .fem.assembly import Assembler
from .fem.material import NeoHookean
from .mesh import TetMesh
from .store import _build_folder, network_table, write_entry
from .surrogate.data import LoadSpec, solve_path
from .surrogate.train import TrainConfig, train

#: the tiny network: the build's own layout (reduced, the physics skip's linear response and POD)
TINY = TrainConfig(hidden=(4,), rank=1, features=1, members=1, epochs=1, batch=4, seed=0)
#: the load a warm-up path grows to, as a share of the scene's: one step Newton takes at once
TINY_LOAD = 1e-3


def warm_up(
    mesh: TetMesh, material: NeoHookean, spec: LoadSpec, scene: dict, store: Path, max_newton: int | None
) -> float:
    """Solve two one-step paths of a tiny load (the data's own solver, which the build's paths in
    this process then reuse), train the tiny network on them and write it, with the build's
    `scene` (its manifest's), into a scratch folder of `store` (removed after). Returns the
    seconds the write took (the entry's files, and their load-back over the scene's mesh, which
    write_entry checks before it installs an entry)."""
    tiny = dataclasses.replace(spec, steps=1, max_force=spec.max_force * TINY_LOAD)
    paths = [solve_path(mesh, material, tiny, i, max_newton=max_newton) for i in (0, 1)]
    F = np.concatenate([p["forces"] for p in paths])
    U = np.concatenate([p["u"] for p in paths])
    P = np.concatenate([np.full(len(p["forces"]), p["index"]) for p in paths])
    if len(np.unique(P)) < 2:  # a first step that failed at a thousandth of the load: the build says why
        return 0.0
    region = np.asarray(spec.region)
    result = train(F, U, P, Assembler(mesh, material), region, TINY, progress=False)
    t0 = time.perf_counter()
    # a locked build folder (hidden: never served): one a killed build leaves is removed by the
    # next scan of the store, as any stale build's (a TemporaryDirectory's stayed for good)
    scratch, lock = _build_folder(store, "warm-up")
    try:
        write_entry(
            scratch, "warm-up", mesh, region, result.model,
            material=material, scene=scene, rebuild="",
            training={"load_distribution": {k: v for k, v in dataclasses.asdict(spec).items() if k != "region"}},
            network=network_table(result.model, TINY.layout, len(region), mesh.n_nodes),
        )  # fmt: skip
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
        if lock is not None:
            os.close(lock)
    return time.perf_counter() - t0

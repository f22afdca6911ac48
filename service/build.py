"""``elastreg train``: a scene in, a verified model-store entry out (above the store it writes).

Data go to a folder keyed by a hash of everything that shapes them (mesh, material, load
distribution), so a rerun resumes the same data set and a changed scene starts a new one.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
import time
from pathlib import Path

import numpy as np

from .fem.assembly import Assembler
from .fem.material import NeoHookean
from .scene import Scene
from .store import write_entry
from .surrogate.data import LoadSpec, generate, load_dataset
from .surrogate.train import TrainConfig, train

log = logging.getLogger(__name__)


def load_spec(scene: Scene, region: np.ndarray) -> LoadSpec:
    t = scene.training
    return LoadSpec(
        region=tuple(int(i) for i in region),
        max_force=float(t.max_force),
        patch_nodes=(int(t.patch_nodes[0]), int(t.patch_nodes[1])),
        steps=int(t.load_steps),
        multi_patch=float(t.multi_patch),
        normal_fraction=float(t.normal_fraction),
        pull_fraction=float(t.pull_fraction),
        twist_fraction=float(t.twist_fraction),
        seed=int(t.seed),
    )


def data_key(mesh_hash: str, material: NeoHookean, spec: LoadSpec) -> str:
    blob = json.dumps([mesh_hash, material.E, material.nu, dataclasses.asdict(spec)], sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:12]


def default_data_root() -> Path:
    env = os.environ.get("ELASTREG_DATA")
    return Path(env) if env else Path.home() / ".cache" / "elastreg" / "data"


@dataclasses.dataclass
class BuildReport:
    entry: Path
    samples: int
    paths: int
    data_seconds: float
    train_seconds: float
    metrics: dict


def build(
    scene: Scene,
    store: Path,
    *,
    samples: int | None = None,
    workers: int = 2,
    scheduler: str | None = None,
    data_root: Path | None = None,
    config: TrainConfig = TrainConfig(),
    command: str = "",
    progress: bool = True,
    name: str | None = None,
) -> BuildReport:
    """Generate (or resume) the scene's data, train, and write the store entry (id: `name`,
    else the scene's name; variants of one scene share its data)."""
    mesh, loaded = scene.build_mesh()
    region = scene.region_nodes(mesh, loaded)
    mat = scene.material
    material = NeoHookean(float(mat.E), float(mat.nu))
    spec = load_spec(scene, region)
    n_samples = int(samples or scene.training.samples)
    n_paths = max(2, math.ceil(n_samples / spec.steps))
    data_dir = Path(data_root or default_data_root()) / f"{scene.name}-{data_key(mesh.hash, material, spec)}"
    log.info("data for %s in %s (%d paths)", scene.name, data_dir, n_paths)

    t0 = time.perf_counter()
    for _ in generate(mesh, material, spec, data_dir, n_paths, workers=workers, scheduler=scheduler, progress=progress):
        pass
    data_seconds = time.perf_counter() - t0
    F, U, P = load_dataset(data_dir, list(range(n_paths)))
    if config.members is None:  # the scene's ensemble is the reduced layout's; the paper's has none
        config = dataclasses.replace(config, members=scene.training.members if config.layout == "reduced" else 1)
    result = train(F, U, P, Assembler(mesh, material), region, config, progress=progress)
    net = result.model
    training = {
        "samples": int(len(F)),
        "paths": n_paths,
        "data_seconds": round(data_seconds, 1),
        "validation": result.metrics,
        "train_seconds": round(result.metrics["train_seconds"], 1),
        "config": dataclasses.asdict(config),
        "load_distribution": {k: v for k, v in dataclasses.asdict(spec).items() if k != "region"},
        "data_key": data_dir.name,
    }
    network = {
        "layout": config.layout,
        "hidden": list(net.hidden),
        "n_in": 3 * len(region),
        "n_out": 3 * mesh.n_nodes,
        "rank": int(net.basis.shape[1]) if hasattr(net, "basis") else None,
        "members": int(getattr(net, "members", 1)),
        "physics_skip": bool(config.physics_skip) if config.layout == "reduced" else False,
    }
    entry = write_entry(
        store, name or scene.name, mesh, region, net,
        material=material,
        scene=json.loads(scene.model_dump_json()),
        training=training,
        network=network,
        rebuild=command,
        renumbered=loaded.kept is not None,
    )  # fmt: skip
    log.info("wrote %s: validation mean %.3f mm, p95 %.3f mm", entry, result.metrics["mean_mm"], result.metrics["p95_mm"])
    return BuildReport(entry, len(F), n_paths, data_seconds, result.metrics["train_seconds"], result.metrics)

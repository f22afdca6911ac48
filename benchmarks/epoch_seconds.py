"""Seconds per training epoch, late in a run, with the weight decay on every parameter (as
before) and on the weight matrices alone (`decay_groups`), with subnormal floats flushed
(`--flush`, as the command line runs) or not. A timed build gets the epochs its clock allows,
so a slower epoch is a worse model. Both arms train the default network on one data folder, one
after the other, from one seed.

    python benchmarks/epoch_seconds.py --scene benchmarks/scenes/phantom_fresh_sites.toml \\
        --data DATA/phantom_fresh_sites-ce4b0f21643a --epochs 700 --out epoch_seconds.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.bench.machine import describe
from service.build import load_spec
from service.config import flush_subnormals
from service.fem.assembly import Assembler
from service.fem.material import NeoHookean
from service.scene import load_scene
from service.surrogate import train as trainer
from service.surrogate.data import done_indices, load_dataset


def every_parameter(model: torch.nn.Module, weight_decay: float) -> list[dict]:
    """The old rule: one group, every parameter decayed."""
    return [{"params": list(model.parameters()), "weight_decay": weight_decay}]


def subnormals(tensors) -> int:
    """How many entries are subnormal float32 (nonzero, under the smallest normal)."""
    tiny = torch.finfo(torch.float32).tiny
    return int(sum(((t.abs() < tiny) & (t != 0)).sum() for t in tensors))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", required=True)
    ap.add_argument("--data", required=True, help="a build's data folder (its path_*.npz)")
    ap.add_argument("--epochs", type=int, default=700)
    ap.add_argument("--flush", action="store_true", help="flush subnormals first, as `elastreg` does")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    if args.flush:
        flush_subnormals()  # before torch's threads exist: each copies its creator's flag
    torch.set_num_threads(2)
    scene = load_scene(args.scene)
    mesh, loaded = scene.build_mesh()
    spec = load_spec(scene, mesh, loaded)
    region = np.asarray(spec.region)
    data = Path(args.data)
    F, U, P = load_dataset(data, sorted(done_indices(data)), len(region), mesh.n_nodes)
    asm = Assembler(mesh, NeoHookean.of(scene.material))
    config = trainer.TrainConfig(epochs=args.epochs, patience=args.epochs, members=1)
    adams: list[torch.optim.Adam] = []

    class Adam(torch.optim.Adam):  # the trainer's own, kept to count its moments' subnormals
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            adams.append(self)

    torch.optim.Adam = Adam  # type: ignore[misc]
    matrices = trainer.decay_groups
    arms = {}
    for arm, rule in (("every parameter", every_parameter), ("weight matrices", matrices)):
        trainer.decay_groups = rule
        result = trainer.train(F, U, P, asm, region, config, progress=False)
        seconds = np.diff([0.0] + [h["seconds"] for h in result.history])
        deciles = [float(np.median(c)) for c in np.array_split(seconds, min(10, len(seconds)))]
        slopes = [m.weight.detach().abs().min().item() for m in result.model.modules() if isinstance(m, torch.nn.PReLU)]
        arms[arm] = {
            "epoch_seconds_by_decile": deciles,
            "validation_mm": result.metrics["mean_mm"],
            "smallest_prelu_slope_by_layer": slopes,
            "adam_first_moment_subnormals": subnormals(s["exp_avg"] for s in adams[-1].state.values()),
        }
        print(f"{arm}: epoch ms by decile {[round(d * 1e3) for d in deciles]}, validation "
              f"{result.metrics['mean_mm']:.3f} mm, smallest PReLU slopes {slopes}, subnormals in "
              f"Adam's first moments {arms[arm]['adam_first_moment_subnormals']}", flush=True)  # fmt: skip
    trainer.decay_groups = matrices
    ratio = (
        arms["every parameter"]["epoch_seconds_by_decile"][-1] / arms["weight matrices"]["epoch_seconds_by_decile"][-1]
    )
    print(f"last decile's epoch: {ratio:.2f}x as long with every parameter decayed")
    if args.out:
        report = {"machine": describe(), "args": {k: str(v) for k, v in vars(args).items()}, "arms": arms,
                  "last_decile_ratio": ratio}  # fmt: skip
        args.out.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()

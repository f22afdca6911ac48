"""An entry's validation figures, recomputed from its data folder with today's code.

The same held-out paths as its build (split_paths with the build's seed and fraction), through
the entry's own forward model (NetworkModel.predict: the physics layout's linear part
included): mean and p95 nodal error, the mean relative error against each sample's whole
displacement, and the u = 0 and linear baselines.

    python benchmarks/revalidate.py STORE/ENTRY DATA_FOLDER
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from service.bench.machine import describe
from service.store import load_entry
from service.surrogate.data import done_indices, load_dataset
from service.surrogate.train import nodal_errors, split_paths


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("entry")
    p.add_argument("data")
    args = p.parse_args()
    entry = load_entry(Path(args.entry))
    cfg = entry.manifest["training"]["config"]
    done = sorted(done_indices(Path(args.data)))
    if len(done) != int(entry.manifest["training"]["paths"]):  # another split: other validation paths
        raise SystemExit(f"{args.data} holds {len(done)} paths, the build used {entry.manifest['training']['paths']}")
    F, U, P = load_dataset(Path(args.data), done)
    _, val = split_paths(P, float(cfg["val_fraction"]), int(cfg["seed"]))
    va = np.isin(P, val)
    model = entry.network
    pred = np.concatenate([model.predict(F[va][i : i + 256], model.region) for i in range(0, int(va.sum()), 256)])
    true = U[va].astype(np.float64)
    e = nodal_errors(pred.reshape(len(pred), -1), true.reshape(len(true), -1))
    lin = model.compliance().displacements(F[va], model.region) if model.physics else None
    flat = true.reshape(len(true), -1)
    out = {
        "entry": str(args.entry),
        "machine": describe(),
        "samples": int(va.sum()),
        "val_mean_mm": float(e.mean() * 1e3),
        "val_p95_mm": float(np.percentile(e, 95) * 1e3),
        "val_relative": float(
            np.mean(np.linalg.norm(pred.reshape(len(pred), -1) - flat, axis=1) / np.linalg.norm(flat, axis=1))
        ),  # fmt: skip
        "zero_mean_mm": float(np.linalg.norm(true, axis=-1).mean() * 1e3),
        "linear_mean_mm": None if lin is None else float(nodal_errors(lin, flat).mean() * 1e3),
    }
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Training variants on one held-out build's data, scored by the forward model's error at tool
sites: the study that chose the physics layout's --features 64 and --weight-decay 1e-4.

Each variant retrains the network for SECONDS on the data of the build at --model (a build of
phantom_held_out.toml: the reported sites' supports kept off), then scores the mean nodal error
of its prediction, given the true forces, against the Newton solution on the same mesh at 5
loads on each of the reported sites' tool patches ("held": held out of the data) and of the 4
calibration sites' ("trained"), beside the linear response's (the third figure of each triple:
mean, median, linear mean). With --cv the paths whose loads touch a calibration site's support
are dropped first and only those sites are scored: a selection set disjoint from the reported
sites (616 of the phantom's 800 paths go, so its figures are a smaller data set's).

    python benchmarks/held_out_variants.py --model STORE/phantom_held_out 240 base feat64 wd
    python benchmarks/held_out_variants.py --model STORE/phantom_held_out --cv 180 base feat64 wd feat64wd

The logs of both runs are in reports/held-out-design/ (variants_*.log).
"""

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from held_out_forward import site_loads

from service.bench.anysite import CALIBRATION_SEED, SITE_SEED, SITES, site_patches, site_region
from service.config import flush_subnormals
from service.fem.assembly import Assembler
from service.fem.rest import rest_compliance
from service.store import load_entry
from service.surrogate import train as T
from service.surrogate.basis import pod_basis
from service.surrogate.model import NetworkModel
from service.surrogate.pathfiles import load_dataset

#: each variant's changes to the settings before this study (256 features, no weight decay),
#: which "base" trains; "universal" also reads every region node's patch response (its features)
OLD: dict[str, Any] = dict(features=256, weight_decay=0.0)
VARIANTS: dict[str, dict[str, Any]] = {
    "base": dict(),
    "universal": dict(),
    "feat64": dict(features=64),
    "small": dict(hidden=(128, 128)),
    "feat16": dict(features=16),
    "feat64wd": dict(features=64, weight_decay=1e-4),
    "wd3e-5": dict(weight_decay=3e-5),
    "wd3e-4": dict(weight_decay=3e-4),
    "feat32": dict(features=32),
    "feat128": dict(features=128),
    "wd": dict(weight_decay=1e-4),
}


def test_loads(entry) -> list[dict]:
    """5 loads and their Newton solutions at each reported site ("held") and 4 calibration sites."""
    return [
        dict(set=label, site=site, tool=tool, f=f, u=u)
        for label, seed, k in (("held", SITE_SEED, SITES), ("trained", CALIBRATION_SEED, 4))
        for site, tool, loads in site_loads(entry, seed, k)
        for f, u in loads
    ]


def score(entry, material, C, tests: list[dict], net, labels: tuple[str, ...]) -> dict:
    """(mean, median, linear mean) nodal error in mm at each label's test loads."""
    m = NetworkModel(entry.mesh, material, entry.region, net, entry.network.E0)
    out = {}
    for label in labels:
        e, el = [], []
        for t in (t for t in tests if t["set"] == label):
            un = m.predict(t["f"][None], t["tool"])[0]
            e.append(np.linalg.norm(un - t["u"], axis=1).mean() * 1e3)
            u1 = C.displacements(t["f"][None], t["tool"])[0].reshape(-1, 3)
            el.append(np.linalg.norm(u1 - t["u"], axis=1).mean() * 1e3)
        out[label] = (float(np.mean(e)), float(np.median(e)), float(np.mean(el)))
    return out


def drop_calibration_paths(mesh, region, F, U, P):
    """The data less every path whose loads touch a calibration site's support: a selection set."""
    rng = np.random.default_rng(CALIBRATION_SEED)
    sup = np.concatenate([s_ for _, _, s_ in site_patches(mesh, site_region(mesh, region, CALIBRATION_SEED), 4, rng)])
    pos = np.flatnonzero(np.isin(region, sup))
    bad = np.unique(P[np.abs(F[:, pos]).sum((1, 2)) > 0])
    keep = ~np.isin(P, bad)
    print(f"CV: {bad.size} of {np.unique(P).size} paths touch the calibration supports; dropped", flush=True)
    return F[keep], U[keep], P[keep]


def universal_features(mesh, C, original):
    """linear_features that also span every region node's unit patch response, 3 axes, scaled to
    the training rows' rms norm."""

    def features(asm, region_, F_, train_, q, seed, chunk=1024):
        _, _, L = original(asm, region_, F_, train_, q, seed, chunk)
        k = 15
        cols = []
        for c in region_:
            patch = mesh.surface_patch(int(c), k)[:k]
            for ax in range(3):
                g = np.zeros((mesh.n_nodes, 3))
                g[patch, ax] = 1.0 / k
                cols.append(g.ravel())
        X = C.solve(np.array(cols).T).T
        scale = np.sqrt((L[train_] ** 2).sum(1).mean()) / np.sqrt((X**2).sum(1).mean())
        basis, _ = pod_basis(np.concatenate([L[train_], (X * scale).astype(np.float32)]), q, seed)
        return (L @ basis.astype(np.float32)), basis, L

    return features


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", required=True, help="a build of benchmarks/scenes/phantom_held_out.toml")
    p.add_argument("--cv", action="store_true", help="drop the calibration sites' paths and score those sites only")
    p.add_argument("seconds", type=float)
    p.add_argument("variants", nargs="*", help=f"of {', '.join(VARIANTS)} (default: all)")
    args = p.parse_args()
    unknown = set(args.variants) - set(VARIANTS)
    if unknown:
        p.error(f"unknown variants {sorted(unknown)}; choose from {list(VARIANTS)}")
    flush_subnormals()  # before torch's threads, as elastreg train: subnormals slowed training 10x
    entry = load_entry(Path(args.model))
    mesh, region = entry.mesh, entry.region
    material = entry.network.material.with_stiffness(entry.network.E0)
    C = rest_compliance(mesh, material)
    tests = test_loads(entry)
    print(len(tests), "test loads", flush=True)
    data_dir = Path.home() / ".cache/elastreg/data" / entry.manifest["training"]["data_key"]
    F, U, P = load_dataset(data_dir, None, len(region), mesh.n_nodes)
    if args.cv:
        F, U, P = drop_calibration_paths(mesh, region, F, U, P)
    labels = ("trained",) if args.cv else ("held", "trained")
    original = T.linear_features
    try:
        for name in args.variants or list(VARIANTS):
            T.linear_features = universal_features(mesh, C, original) if name == "universal" else original
            cfg = T.TrainConfig(members=1, epochs=100000, max_seconds=args.seconds, **{**OLD, **VARIANTS[name]})
            t0 = time.perf_counter()
            trained = T.train(F, U, P, Assembler(mesh, material), region, cfg, progress=False)
            s = score(entry, material, C, tests, trained.model, labels)
            row = dict(
                variant=name,
                seconds=round(time.perf_counter() - t0),
                val_mm=round(trained.metrics["mean_mm"], 4),
                epochs=trained.metrics["epochs"],
                **{k: [round(x, 4) for x in v] for k, v in s.items()},
            )
            print(json.dumps(row), flush=True)
    finally:
        T.linear_features = original
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

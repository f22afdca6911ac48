"""Surrogate accuracy against the number of training samples, and the design comparison.

    python benchmarks/surrogate_study.py DATA_DIR [--out reports/latest] [--sizes 1000 2000 ...]

DATA_DIR is a data folder that `elastreg train benchmarks/scenes/liver_paper.toml` filled (the
store entry's manifest names it: training.data_key). Every network is trained on a subset of whole
load paths and validated on 10 % of the paths it is given (mean and p95 nodal error), and scored on
the paper's recorded sequence given its true forces (a test set from another solver, the same for
every row). Writes
surrogate.md, surrogate.csv and figures/surrogate_samples.png.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from service.bench.cases import LIVER, liver_paper_case
from service.fem.assembly import Assembler
from service.fem.material import NeoHookean
from service.optional import need
from service.scene import load_scene
from service.surrogate.data import load_dataset
from service.surrogate.model import NetworkModel
from service.surrogate.train import TrainConfig, evaluate, split_paths, train

ROOT = Path(__file__).resolve().parents[1]


def paper_test_set(mesh, region):
    seq = LIVER / "sequences" / "neohookean" / "s1"
    tool = np.loadtxt(seq / "tool-vertices-default.txt").astype(np.int64)
    forces = np.load(seq / "true-forces.npy")
    pos = np.full(mesh.n_nodes, -1)
    pos[region] = np.arange(region.size)
    F = np.zeros((len(forces), region.size, 3), np.float32)
    F[:, pos[tool]] = (forces / tool.size)[:, None, :]
    U = (np.load(seq / "positions-default.npy") - mesh.nodes[None]).astype(np.float32)
    return F, U


def forward_ms(model: NetworkModel, support, nodes, repeats: int = 200) -> tuple[float, float]:
    """Median time of one forward pass, and of forward + pullback, on the registration's slices."""
    op = model.restrict(support, nodes)
    g = np.random.default_rng(0).normal(scale=0.05, size=(support.size, 3))
    u_bar = np.ones((nodes.size, 3))
    fwd, both = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        _, pull = op(g)
        t1 = time.perf_counter()
        pull(u_bar)
        t2 = time.perf_counter()
        fwd.append(t1 - t0)
        both.append(t2 - t0)
    return 1e3 * float(np.median(fwd)), 1e3 * float(np.median(both))


def _row(val: dict, skip: bool, train_s: float, test: dict, model: NetworkModel, support, nodes) -> dict:
    """One line of the table (printed as it comes): validation figures, the paper-frame test, times."""
    fwd, both = forward_ms(model, support, nodes)
    row = {"samples": val["train_samples"], "physics_skip": skip, "val_mean_mm": val["mean_mm"],
           "val_p95_mm": val["p95_mm"], "val_relative": val["relative"], "paper_mean_mm": test["mean_mm"],
           "paper_p95_mm": test["p95_mm"], "train_s": train_s, "epochs": val["epochs"],
           "forward_ms": fwd, "forward_pullback_ms": both}  # fmt: skip
    print(json.dumps(row), flush=True)
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("data")
    p.add_argument("--out", default=str(ROOT / "reports" / "latest"))
    p.add_argument("--sizes", type=int, nargs="+", default=[1000, 2000, 4000, 8000, 15000])
    p.add_argument("--skip-sizes", type=int, nargs="*", default=[1000, 4000, 15000])
    p.add_argument("--store", default=None, help="also score these trained entries (--models) on the paper's frames")
    p.add_argument("--models", nargs="*", default=["liver_paper", "liver_paper_skip"])
    args = p.parse_args()
    torch.set_num_threads(int(os.environ.get("ELASTREG_STUDY_THREADS", "2")))
    scene = load_scene(ROOT / "benchmarks" / "scenes" / "liver_paper.toml")
    mesh, loaded = scene.build_mesh()
    region = scene.region_nodes(mesh, loaded)
    asm = Assembler(mesh, NeoHookean.of(scene.material))
    F, U, P = load_dataset(args.data)
    train_paths, val_paths = split_paths(P, 0.1, 0)
    Ft, Ut = paper_test_set(mesh, region)
    case = liver_paper_case()
    match_nodes = np.unique(case.matching)
    rows = []
    for n, skip in [(n, False) for n in args.sizes] + [(n, True) for n in args.skip_sizes]:
        keep = np.isin(P, np.concatenate([train_paths[: max(1, n // 5)], val_paths]))  # train() splits again
        t0 = time.perf_counter()
        res = train(F[keep], U[keep], P[keep], asm, region, TrainConfig(physics_skip=skip), progress=False)
        seconds = time.perf_counter() - t0
        test = evaluate(res.model, Ft, Ut)
        model = NetworkModel(mesh, asm.material, region, res.model, E0=asm.material.E)
        rows.append(_row(res.metrics, skip, seconds, test, model, case.support, match_nodes))
    if args.store:  # the full builds: their own validation figures, the same test
        from service.store import load_entry

        for name in args.models:
            entry = load_entry(Path(args.store) / name)
            v = entry.manifest["training"]["validation"]
            test = evaluate(entry.network.net, Ft, Ut)
            skip = bool(entry.manifest["network"]["physics_skip"])
            rows.append(_row(v, skip, v["train_seconds"], test, entry.network, case.support, match_nodes))
    out = Path(args.out)
    (out / "figures").mkdir(parents=True, exist_ok=True)
    with open(out / "surrogate.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    _plot(rows, out / "figures" / "surrogate_samples.png")
    md = ["# Surrogate accuracy against training samples (the paper's liver)\n",
          "Mean and 95th-percentile nodal error on held-out load paths (validation) and on the paper's recorded "
          "sequence given its true forces (test: another solver's frames). 2 x 512 PReLU, 128 POD modes; trained "
          "on 2 CPU cores. Forward times on the registration's slices (60-node support, matching-surface nodes), "
          "one sample, NumPy float32.\n",
          "| samples | physics skip | val mean (mm) | val p95 (mm) | paper frames mean (mm) | paper p95 (mm) "
          "| train (s) | forward (ms) | forward + pullback (ms) |",
          "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for r in rows:
        md.append(f"| {r['samples']} | {'yes' if r['physics_skip'] else 'no'} | {r['val_mean_mm']:.3f} | "
                  f"{r['val_p95_mm']:.3f} | {r['paper_mean_mm']:.3f} | {r['paper_p95_mm']:.3f} | {r['train_s']:.0f} | "
                  f"{r['forward_ms']:.3f} | {r['forward_pullback_ms']:.3f} |")  # fmt: skip
    md.append("\n![accuracy against samples](figures/surrogate_samples.png)\n")
    (out / "surrogate.md").write_text("\n".join(md))
    print(f"wrote {out / 'surrogate.md'}")


def _plot(rows, path) -> None:
    matplotlib = need("matplotlib", "the surrogate study's figure")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for skip, style in ((False, "-"), (True, "--")):
        rs = sorted((r for r in rows if r["physics_skip"] == skip), key=lambda r: r["samples"])
        if not rs:
            continue
        n = [r["samples"] for r in rs]
        lab = "with physics skip" if skip else "default"
        ax.plot(n, [r["val_mean_mm"] for r in rs], "o" + style, color="tab:blue", label=f"validation mean ({lab})")
        ax.plot(n, [r["val_p95_mm"] for r in rs], "s" + style, color="tab:orange", label=f"validation p95 ({lab})")
        ax.plot(n, [r["paper_mean_mm"] for r in rs], "^" + style, color="tab:green", label=f"paper frames mean ({lab})")
    for target in (0.5, 1.5):
        ax.axhline(target, color="grey", lw=0.8, ls=":")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("training samples")
    ax.set_ylabel("nodal error (mm)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()

"""The forward model alone at a draw's tool sites: each site's mean nodal error of the network
and of the linear response, against the Newton solution on the same mesh, given the true forces.

Registration hides part of a forward model's error (it fits the cloud with whatever forces do
it); this shows it whole, and splits it: `remainder_floor_mm` is what the network's output basis
cannot hold of the truth's remainder over the linear response, `feature_loss` the share of the
linear response its input basis loses. Five loads per site (a tool patch, 30-100 % of the force
that moves the organ about 5 cm by its linear response, a direction near the patch's normal),
from the draw's seed; a site is "held out" where the entry's build kept every training load off
its tool patch.

    python benchmarks/held_out_forward.py --model STORE/phantom_held_out --seed 2026 \\
        --out reports/held-out-design/forward_phantom_held_out.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.bench.anysite import SITES, peak_for_reach, site_patches, site_region
from service.bench.cases import held_out
from service.bench.machine import describe
from service.config import limit_threads
from service.store import load_entry

LEVELS = (0.3, 0.5, 0.7, 0.85, 1.0)


def site_loads(entry, seed: int, sites: int) -> list[tuple[int, np.ndarray, list[tuple[np.ndarray, np.ndarray]]]]:
    """The draw's sites with their test loads: (site, tool patch, [(forces (k, 3), the Newton
    solution (n, 3))]) for each LEVELS load whose solve converged."""
    mesh, C = entry.mesh, entry.network.compliance()
    max_force = float(entry.manifest["training"]["load_distribution"]["max_force"])
    out = []
    rng = np.random.default_rng(seed)
    for site, tool, _ in site_patches(mesh, site_region(mesh, entry.region, seed), sites, rng):
        peak = peak_for_reach(C, tool, 0.05, max_force)
        normal, turn = mesh.patch_normal(tool), np.random.default_rng(site + 7)
        loads = []
        for level in LEVELS:
            d = normal + 0.6 * turn.normal(size=3)
            f = np.tile(d / np.linalg.norm(d) * peak * level / tool.size, (tool.size, 1))
            res = entry.fem.solve(f, tool)
            if res.converged:
                loads.append((f, res.u.reshape(-1, 3)))
        out.append((site, tool, loads))
    return out


def site_rows(entry, seed: int, sites: int) -> list[dict]:
    model = entry.network
    net, C = model.net, model.compliance()
    B, Fb = net.basis.double().numpy(), net.feature_basis.double().numpy()
    rows = []
    for site, tool, loads in site_loads(entry, seed, sites):
        err: dict[str, list[float]] = {"network": [], "linear": [], "floor": [], "feature_loss": []}
        for f, u in loads:
            lin = C.displacements(f[None], tool)[0]
            net_u = model.predict(f[None], tool)[0]
            rem = u.ravel() - lin
            err["network"].append(1e3 * float(np.linalg.norm(net_u - u, axis=1).mean()))
            err["linear"].append(1e3 * float(np.linalg.norm(lin.reshape(-1, 3) - u, axis=1).mean()))
            err["floor"].append(1e3 * float(np.linalg.norm((rem - B @ (B.T @ rem)).reshape(-1, 3), axis=1).mean()))
            err["feature_loss"].append(float(np.linalg.norm(lin - Fb @ (Fb.T @ lin)) / np.linalg.norm(lin)))
        rows.append({
            "site": site,
            "held_out": held_out(entry, tool) or "trained",
            "loads": len(err["network"]),
            "network_mm": float(np.mean(err["network"])),
            "linear_mm": float(np.mean(err["linear"])),
            "remainder_floor_mm": float(np.mean(err["floor"])),
            "feature_loss": float(np.mean(err["feature_loss"])),
        })  # fmt: skip
        r = rows[-1]
        print(f"site {site:>5} ({r['held_out']}): network {r['network_mm']:.3f} mm, linear {r['linear_mm']:.3f} mm, "
              f"floor {r['remainder_floor_mm']:.3f} mm, feature loss {r['feature_loss']:.3f}", flush=True)  # fmt: skip
    return rows


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", required=True, help="a store entry of the physics layout")
    p.add_argument("--seed", type=int, required=True, help="the sites' draw (2026: the reported sites)")
    p.add_argument("--sites", type=int, default=SITES)
    p.add_argument("--out", required=True)
    args = p.parse_args()
    limit_threads(1)
    entry = load_entry(Path(args.model))
    rows = site_rows(entry, args.seed, args.sites)
    config = entry.manifest["training"]["config"]
    summary = {"network_mean_mm": float(np.mean([r["network_mm"] for r in rows])),
               "linear_mean_mm": float(np.mean([r["linear_mm"] for r in rows]))}  # fmt: skip
    print(f"mean over sites: network {summary['network_mean_mm']:.3f} mm, linear {summary['linear_mean_mm']:.3f} mm")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({
        "machine": describe(), "model": Path(args.model).name, "seed": args.seed,
        "features": config["features"], "weight_decay": config["weight_decay"],
        "validation_mm": entry.manifest["training"]["validation"]["mean_mm"], **summary, "rows": rows,
    }, indent=1))  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""What a held-out build's training data load: reads every path file of its data folder (the
forces alone) and counts the paths with force on a kept-off node, the region nodes ever loaded,
and, per reported site of the any-site part, how far its tool patch lies from the nearest node
any training load touched (straight-line, mm).

    python benchmarks/kept_off_in_data.py --scene benchmarks/scenes/liver_paper_held_out.toml \\
        --data ~/.cache/elastreg/data/liver_paper_held_out-KEY

The data folder's name is in the build's manifest (training.data_key).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from service.bench.anysite import SITE_SEED, SITES, site_patches, site_region
from service.scene import resolve_scene


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", required=True, help="the held-out scene the build was made from")
    p.add_argument("--data", required=True, type=Path, help="the build's data folder")
    args = p.parse_args()
    scene = resolve_scene(args.scene)
    mesh, loaded = scene.build_mesh()
    region, kept = scene.region_nodes(mesh, loaded), scene.keep_off_nodes(mesh, loaded)
    on_kept = np.isin(region, kept)
    files = sorted(args.data.glob("path_*.npz"))
    touching = samples = 0
    reached = np.zeros(region.size, bool)
    for f in files:
        with np.load(f) as z:
            forces = z["forces"]
        samples += len(forces)
        loaded_here = np.abs(forces).sum(axis=(0, 2)) > 0
        touching += int(loaded_here[on_kept].any())
        reached |= loaded_here
    print(f"{scene.name}: {len(files)} paths, {samples} samples; paths with force on a kept-off node: {touching}")
    print(f"  region nodes ever loaded: {reached.sum()} of {region.size} ({(~on_kept).sum()} not kept off)")
    tree = cKDTree(mesh.nodes[region[reached]])
    sites = site_patches(mesh, site_region(mesh, region, SITE_SEED), SITES, np.random.default_rng(SITE_SEED))
    for site, tool, _ in sites:
        gap = 1e3 * float(tree.query(mesh.nodes[tool])[0].min())
        print(f"  reported site {site}: its tool patch {gap:.1f} mm from the nearest node a training load touched")


if __name__ == "__main__":
    main()

"""How often a whole-surface build's training paths load the any-site part's reported sites:
replays the trainer's own load sampler (surrogate/data.py sample_path_load, each path's rng
[seed, index], the scene's keep_off included) over a scene's first PATHS paths and counts, per
reported site (SITE_SEED), the paths that load at least half its tool patch and those that load
its centre node. A build without keep_off holds out loads and truth, not sites: this says how
far; on a held-out scene (liver_paper_held_out.toml) every count is 0.

    python benchmarks/sites_in_training.py [--scene benchmarks/scenes/liver_paper.toml] [--paths 3481]

(3,481 paths: the 60-minute liver build's 17,405 samples at 5 load steps.)
"""

from __future__ import annotations

import argparse

import numpy as np

from service.bench.anysite import SITE_SEED, SITES, site_patches, site_region
from service.build import load_spec
from service.scene import load_scene
from service.surrogate.data import sample_path_load


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="benchmarks/scenes/liver_paper.toml")
    p.add_argument("--paths", type=int, default=3481)
    args = p.parse_args()
    scene = load_scene(args.scene)
    mesh, loaded = scene.build_mesh()
    region = scene.region_nodes(mesh, loaded)
    spec = load_spec(scene, mesh, loaded)
    sites = site_patches(mesh, site_region(mesh, region, SITE_SEED), SITES, np.random.default_rng(SITE_SEED))
    nodes = np.asarray(spec.region)
    hits = np.zeros((len(sites), 2), int)  # half the tool patch, the centre node
    for i in range(args.paths):
        loaded_now = np.zeros(mesh.n_nodes, bool)
        loaded_now[nodes[np.abs(sample_path_load(mesh, spec, np.random.default_rng([spec.seed, i]))).sum(1) > 0]] = True
        hits += [(loaded_now[tool].mean() >= 0.5, loaded_now[site]) for site, tool, _ in sites]
    print(f"{args.paths} training paths of {scene.name}, tool patches of {sites[0][1].size} nodes")
    for (site, _, _), (half, centre) in zip(sites, hits, strict=True):
        print(f"  reported site {site}: {half} paths load half its tool patch or more, {centre} its centre node")


if __name__ == "__main__":
    main()

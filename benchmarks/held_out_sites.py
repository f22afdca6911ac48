"""The nodes a build keeps its training loads off so that the any-site part's reported sites
are held out of it: the union of the supports of the SITES sites the part draws (SITE_SEED,
over the scene's load region) and of the scene's own [registration] support (the recorded
sequence's), written in the mesh file's node ids for `[training] keep_off_file`.

    python benchmarks/held_out_sites.py --scene benchmarks/scenes/liver_paper.toml \
        --out benchmarks/scenes/liver_paper_held_out.npy
    python benchmarks/held_out_sites.py --scene phantom --out benchmarks/scenes/phantom_held_out.npy

`--seed` keeps off another draw's sites instead (a draw other than the reported one keeps off
the reported supports, anysite.site_region), for a test at sites nothing was chosen on.

The held-out scenes (liver_paper_held_out.toml, phantom_held_out.toml) are their recipes with
that key and their own names; `elastreg bench anysite` on its build marks each site whose support no training load
touched ("held out"), read from the build's manifest, not from this script.
"""

from __future__ import annotations

import argparse

import numpy as np

from service.bench.anysite import SITE_SEED, SITES, site_patches, site_region
from service.scene import Scene, resolve_scene


def held_out_nodes(scene: Scene, seed: int = SITE_SEED) -> tuple[np.ndarray, bool]:
    """The supports of the SITES sites drawn from `seed` (the reported ones by default) and, for
    the reported draw, the scene's support (if it names one: the second value), in the mesh
    file's ids. Shape: (k,)."""
    mesh, loaded = scene.build_mesh()
    region = scene.region_nodes(mesh, loaded)
    sites = site_patches(mesh, site_region(mesh, region, seed), SITES, np.random.default_rng(seed))
    support = scene.support_nodes(mesh, loaded) if seed == SITE_SEED else None
    nodes = np.unique(np.concatenate([s for _, _, s in sites] + ([] if support is None else [support])))
    return np.sort(loaded.mesh_to_source()[nodes]), support is not None  # surface nodes: each has a file id


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="benchmarks/scenes/liver_paper.toml", help="a .toml file or a builtin scene")
    p.add_argument("--out", required=True, help="the .npy file to write")
    p.add_argument(
        "--seed",
        type=int,
        default=SITE_SEED,
        help=f"the draw whose sites are kept off (default: {SITE_SEED}, the reported)",
    )
    args = p.parse_args()
    scene = resolve_scene(args.scene)
    nodes, own = held_out_nodes(scene, args.seed)
    np.save(args.out, nodes.astype(np.int64))
    also = " and the scene's own" if own else ""
    which = "reported" if args.seed == SITE_SEED else f"seed {args.seed}'s"
    print(f"{scene.name}: {nodes.size} nodes kept off (the supports of {SITES} {which} sites{also})")


if __name__ == "__main__":
    main()

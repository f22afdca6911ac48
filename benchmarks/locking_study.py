"""How much stiffer the coarse liver is than its refinement: the force bias it puts on registration.

The anysite part scores registration against the Neo-Hookean solution on the liver subdivided
once. At nu = 0.49 linear tets lock (volumetric locking): the coarse mesh is stiffer, so a
method that runs on it needs more force for the same displacement, whatever its forward model.
This measures that bias without any registration: at each site, a load over the tool patch
(outward normal, as the anysite generator pulls) on the coarse mesh and on the fine one, linear
elasticity, and the compliance ratio kappa = <u_c, u_f> / <u_c, u_c> over the coarse nodes. A
method exact on the coarse mesh overestimates the force by about kappa. With --registered it
also registers the calibration sites' sequences (CALIBRATION_SEED, 3026, never reported) with the network
and prints each frame's |f_est| / |f_true| and the angle between them.

With --scene and --nu it needs no model: kappa at the calibration sites for each Poisson's ratio.
Locking grows as nu nears 0.5, plain coarseness does not, so kappa against nu tells which of the
two makes the coarse mesh stiff (and so whether a locking-free element would remove the bias).

    python benchmarks/locking_study.py --model /path/to/store/liver_anysite [--registered]
    python benchmarks/locking_study.py --scene benchmarks/scenes/liver_paper.toml --nu 0.3 0.4 0.45 0.49
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.bench.anysite import CALIBRATION_SEED, NETWORK_LM, SITE_SEED, anysite_cases, site_patches, site_region
from service.bench.machine import describe
from service.bench.truth import fine_patch, subdivide
from service.config import limit_threads
from service.fem.material import NeoHookean
from service.fem.rest import rest_compliance
from service.registration.session import Session
from service.scene import load_scene
from service.store import load_entry


def tools(entry, sites: int, seed: int) -> list:
    """The anysite generator's tool patches for `seed` (its draws, in its order)."""
    region = site_region(entry.mesh, entry.region, seed)  # calibration sites keep off the reported ones
    return [(site, tool) for site, tool, _ in site_patches(entry.mesh, region, sites, np.random.default_rng(seed))]


def scene_entry(path: str, nu: float) -> SimpleNamespace:
    """What tools() and compliance_ratios() read of an entry, from a scene at Poisson's ratio nu."""
    scene = load_scene(path)
    mesh, loaded = scene.build_mesh()
    material = NeoHookean(float(scene.material.E), nu)
    return SimpleNamespace(mesh=mesh, region=scene.region_nodes(mesh, loaded), fem=SimpleNamespace(material=material))


def patch_kappa(coarse, fine, coarse_c, fine_c, patch, normal) -> float:
    """<u_c, u_f> / <u_c, u_c> over the coarse nodes, for a unit load along `normal` spread over
    `patch` on the coarse mesh and over its area on the fine one."""
    spread = fine_patch(coarse, fine, patch)
    u_c = coarse_c.displacements(np.tile(normal / patch.size, (1, patch.size, 1)), patch)[0]
    u_f = fine_c.displacements(np.tile(normal / spread.size, (1, spread.size, 1)), spread)[0]
    u_f = u_f[: 3 * coarse.n_nodes]  # the coarse nodes keep their ids on the fine mesh
    return float(u_c @ u_f / (u_c @ u_c))


def outward(mesh, tool) -> np.ndarray:
    normal = mesh.vertex_normals[tool].sum(axis=0)
    return normal / np.linalg.norm(normal)


def compliance_ratios(entry, sites: int, seed: int, fine=None) -> list[dict]:
    mesh, material = entry.mesh, entry.fem.material
    fine = subdivide(mesh) if fine is None else fine
    coarse_c, fine_c = rest_compliance(mesh, material), rest_compliance(fine, material)
    return [{"seed": seed, "site": site, "kappa": patch_kappa(mesh, fine, coarse_c, fine_c, tool, outward(mesh, tool))}
            for site, tool in tools(entry, sites, seed)]  # fmt: skip


def truth_ratios(entry, sites: int, seed: int) -> list[dict]:
    """kappa one level up: the truth's mesh (subdivided once) against its own refinement, with the
    same patch loads. How far the truth itself is from a converged solution."""
    mesh, material = entry.mesh, entry.fem.material
    fine = subdivide(mesh)
    finer = subdivide(fine)
    fine_c, finer_c = rest_compliance(fine, material), rest_compliance(finer, material)
    rows = []
    for site, tool in tools(entry, sites, seed):
        spread = fine_patch(mesh, fine, tool)  # the truth's load over the tool patch
        kappa = patch_kappa(fine, finer, fine_c, finer_c, spread, outward(mesh, tool))
        rows.append({"seed": seed, "site": site, "kappa_truth": kappa})
    return rows


def registered_ratios(entry, sites: int) -> list[dict]:
    rows = []
    for case in anysite_cases(entry, sites=sites, frames=8, seed=CALIBRATION_SEED):
        config = dataclasses.replace(NETWORK_LM, support=tuple(int(i) for i in case.support))
        session = Session(entry.network, config)
        for k, cloud in enumerate(case.clouds):
            f, t = session.frame(cloud).net_force, case.net_forces[k]
            cos = float(f @ t / (np.linalg.norm(f) * np.linalg.norm(t)))
            rows.append({"case": case.name, "frame": k, "ratio": float(np.linalg.norm(f) / np.linalg.norm(t)),
                         "angle_deg": float(np.degrees(np.arccos(np.clip(cos, -1, 1))))})  # fmt: skip
    return rows


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", help="a whole-surface store entry of the paper's liver")
    p.add_argument("--scene", help="instead of a model: a scene, for kappa against --nu")
    p.add_argument("--nu", type=float, nargs="+", default=[0.3, 0.4, 0.45, 0.49])
    p.add_argument("--truth", action="store_true", help="with --scene: the truth's mesh against its refinement")
    p.add_argument("--registered", action="store_true", help="also register the calibration sites")
    p.add_argument("--out", default=str(ROOT / "reports" / "locking" / "locking.json"))
    args = p.parse_args()
    limit_threads(1)
    if args.scene:
        name = "locking_truth.json" if args.truth else "locking_nu.json"
        return scene_study(args.scene, args.nu, Path(args.out).with_name(name), args.truth)
    if not args.model:
        p.error("--model or --scene is required")
    entry = load_entry(Path(args.model))
    result: dict = {"machine": describe(), "model": Path(args.model).name}
    result["kappa"] = compliance_ratios(entry, 4, CALIBRATION_SEED) + compliance_ratios(entry, 6, SITE_SEED)
    for r in result["kappa"]:
        which = "calibration" if r["seed"] == CALIBRATION_SEED else "anysite (reported)"
        print(f"{which:>18} site node {r['site']:5d}: coarse mesh stiffer by kappa = {r['kappa']:.3f}")
    if args.registered:
        result["registered"] = registered_ratios(entry, 4)
        for r in result["registered"]:
            print(
                f"{r['case']} frame {r['frame']}: |f_est| / |f_true| = {r['ratio']:.2f}, angle {r['angle_deg']:.1f} deg"
            )
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    return 0


def scene_study(scene: str, nus: list[float], out: Path, truth: bool) -> int:
    """kappa at the calibration sites for each nu: the scene's mesh against its refinement, or
    (`truth`) that refinement against its own."""
    result: dict = {"machine": describe(), "scene": scene, "seed": CALIBRATION_SEED, "rows": []}
    fine = None
    for nu in nus:
        entry = scene_entry(scene, nu)
        if truth:
            rows = truth_ratios(entry, 4, CALIBRATION_SEED)
        else:
            fine = subdivide(entry.mesh) if fine is None else fine  # the mesh is the same for every nu
            rows = compliance_ratios(entry, 4, CALIBRATION_SEED, fine)
        for r in rows:
            result["rows"].append({"nu": nu, **r})
            what = "the truth's mesh stiffer than its refinement by" if truth else "kappa ="
            value = r["kappa_truth"] if truth else r["kappa"]
            print(f"nu {nu:.3f}, calibration site node {r['site']:5d}: {what} {value:.3f}", flush=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

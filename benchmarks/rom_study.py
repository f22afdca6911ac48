"""A projection-based reduced-order model (ROM) of the Neo-Hookean P1 equations, measured beside
the network on a new organ's held-out test set: the issue's untried candidate.

    python benchmarks/rom_study.py --scene benchmarks/scenes/liver_deepphysx.toml \
        [--data-seconds 360] [--ranks 16 32 64] [--network-minutes 10] [--out FILE]

The ROM: a POD basis V (r columns) of a timed build's training displacements (the scene's load
paths, seed 0, Newton capped as a timed build caps it), and the Galerkin equations
V^T f_int(V q) = V^T g solved by Newton in q with an energy line search. Hyper-reduced by ECSW
(energy-conserving sampling and weighting, Farhat et al. 2014): a few tets with non-negative
weights whose reduced forces match the whole mesh's on training snapshots to ECSW_TOL, so a
Newton iteration costs the sampled tets, not the mesh.

Scored on `elastreg bench minutes`' test set (TEST_SEED, uncapped, 40 paths), which nothing here
chose anything on: relative error |u - u_true| / |u_true| per sample, as that part reports it.
Beside it: the best any ROM on that basis can do (the test displacements' orthogonal projection
onto V), and, with --network-minutes, `elastreg train SCENE --minutes M` from an empty data
folder scored on the same test set (the build-minutes part's timed_build).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.linalg as sla
from scipy.optimize import nnls

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.bench.machine import describe
from service.bench.minutes import test_set, timed_build
from service.build import TIMED_NEWTON_CAP, data_key, load_spec
from service.config import limit_threads
from service.fem.assembly import deformation_gradient, neo_hookean_element_stiffness
from service.fem.material import NeoHookean
from service.scene import load_scene
from service.surrogate.data import done_indices, generate, load_dataset

#: ECSW's tolerance on the snapshots' reduced forces (relative), the value its authors use
ECSW_TOL = 1e-2
#: training snapshots the ECSW fit matches (a random draw, seed 0)
ECSW_SNAPSHOTS = 60
#: Newton's stop: the reduced residual under this share of the reduced load
NEWTON_RTOL = 1e-6


class ReducedModel:
    """Galerkin ROM on span(V), integrated over tets `elems` with weights `w` (all tets, weight 1,
    for the unreduced ROM)."""

    def __init__(self, mesh, material: NeoHookean, V: np.ndarray, elems: np.ndarray, w: np.ndarray):
        self.material, self.V = material, V
        full = np.zeros((3 * mesh.n_nodes, V.shape[1]))
        full[mesh.free_dofs] = V
        tets = mesh.tets[elems]
        self.Ve = full.reshape(mesh.n_nodes, 3, -1)[tets].reshape(len(elems), 12, -1)  # (s, 12, r)
        self.grads = mesh.shape_gradients[elems]
        self.wvol = mesh.volumes[elems] * w

    def _F(self, q: np.ndarray) -> np.ndarray:
        ue = (self.Ve @ q).reshape(-1, 4, 3)
        F = np.matmul(ue.transpose(0, 2, 1), self.grads)
        F[:, [0, 1, 2], [0, 1, 2]] += 1.0
        return F

    def energy(self, q: np.ndarray) -> float:
        return float(self.wvol @ self.material.energy(self._F(q)))

    def force_tangent(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """V^T f_int(V q) (r,) and V^T K(V q) V (r, r), one GEMM for the tangent."""
        F = self._F(q)
        fe = np.matmul(self.grads, self.material.stress(F).transpose(0, 2, 1)).reshape(-1, 12) * self.wvol[:, None]
        Ke = neo_hookean_element_stiffness(self.material, F, self.grads, self.wvol).reshape(-1, 12, 12)
        r = self.Ve.shape[2]
        KV = np.matmul(Ke, self.Ve).reshape(-1, r)
        return np.einsum("sd,sdr->r", fe, self.Ve), self.Ve.reshape(-1, r).T @ KV

    def solve(self, fr: np.ndarray, q: np.ndarray, max_iter: int = 40) -> tuple[np.ndarray, int]:
        """Equilibrium under reduced load fr from q; (q, Newton iterations)."""
        scale = max(float(np.linalg.norm(fr)), 1e-300)
        value = self.energy(q) - fr @ q
        for it in range(max_iter):
            fi, Kr = self.force_tangent(q)
            R = fi - fr
            if np.linalg.norm(R) <= NEWTON_RTOL * scale:
                return q, it
            try:
                dq = -sla.solve(Kr, R, assume_a="pos")
            except (sla.LinAlgError, ValueError):
                dq = -np.linalg.lstsq(Kr, R, rcond=None)[0]
            step = 1.0
            while step > 1e-6:  # backtrack until the energy falls (Armijo)
                trial = self.energy(q + step * dq) - fr @ (q + step * dq)
                if np.isfinite(trial) and trial <= value + 1e-4 * step * (R @ dq):
                    break
                step *= 0.5
            else:
                return q, it + 1  # no descent left at working precision
            q, value = q + step * dq, trial
        return q, max_iter


def element_forces(mesh, material: NeoHookean, u: np.ndarray, V: np.ndarray) -> np.ndarray:
    """Each tet's reduced internal force V_e^T f_e(u). Shape: (t, r)."""
    F = deformation_gradient(u, mesh.tets, mesh.shape_gradients)
    P = material.stress(F) * mesh.volumes[:, None, None]
    fe = np.matmul(mesh.shape_gradients, P.transpose(0, 2, 1)).reshape(-1, 12)
    full = np.zeros((3 * mesh.n_nodes, V.shape[1]))
    full[mesh.free_dofs] = V
    Ve = full.reshape(mesh.n_nodes, 3, -1)[mesh.tets].reshape(len(mesh.tets), 12, -1)
    return np.einsum("td,tdr->tr", fe, Ve)


def ecsw(G: np.ndarray, b: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Greedy sparse non-negative least squares: few columns of G, weights w >= 0, with
    |G w - b| <= tol |b|. Each round adds the columns most aligned with the residual (a tenth of
    those held, at least one) and refits; columns the fit zeroes leave."""
    chosen, w = np.zeros(0, np.int64), np.zeros(0)
    unit = G / np.maximum(np.linalg.norm(G, axis=0), 1e-300)
    res = b.copy()
    while np.linalg.norm(res) > tol * np.linalg.norm(b) and chosen.size < G.shape[1]:
        score = unit.T @ res
        score[chosen] = -np.inf
        new = np.argsort(score)[-(chosen.size // 10 + 1) :]
        new = new[score[new] > 0]
        if not new.size:  # no column lowers the residual: the fit is as close as it gets
            break
        chosen = np.concatenate([chosen, new])
        w, _ = nnls(G[:, chosen], b, maxiter=50 * chosen.size)
        chosen, w = chosen[w > 0], w[w > 0]
        res = b - G[:, chosen] @ w
    return chosen, w


def training_data(scene, seconds: float, root: Path) -> Path:
    """A timed build's training paths (seed 0, Newton capped) for `seconds` of 2 workers, kept."""
    mesh, loaded = scene.build_mesh()
    material = NeoHookean.of(scene.material)
    spec = load_spec(scene, mesh, loaded)
    folder = root / f"{scene.name}-train-{data_key(mesh.hash, material, spec, TIMED_NEWTON_CAP)}"
    if not done_indices(folder):
        until = time.perf_counter() + seconds
        for _ in generate(mesh, material, spec, folder, 10**6, workers=2, progress=False,
                          max_newton=TIMED_NEWTON_CAP, until=until):  # fmt: skip
            pass
    return folder


def score_rom(rom: ReducedModel, mesh, region, F, Y, paths) -> dict:
    """Relative errors on the test set, each path's steps solved in turn from the last."""
    free, r = mesh.free_dofs, rom.V.shape[1]
    rel, iterations, seconds = np.full(len(F), np.nan), [], []
    for p in np.unique(paths):
        q = np.zeros(r)
        for i in np.flatnonzero(paths == p):
            g = np.zeros((mesh.n_nodes, 3))
            g[region] = F[i]
            t0 = time.perf_counter()
            q, its = rom.solve(rom.V.T @ g.reshape(-1)[free], q)
            seconds.append(time.perf_counter() - t0)
            iterations.append(its)
            rel[i] = np.linalg.norm(rom.V @ q - Y[:, i]) / np.linalg.norm(Y[:, i])
    t0, n = time.perf_counter(), 20
    for _ in range(n):
        rom.force_tangent(q)
    return {
        "relative_mean": float(np.mean(rel)),
        "relative_median": float(np.median(rel)),
        "relative_p95": float(np.percentile(rel, 95)),
        "newton_iterations_median": float(np.median(iterations)),
        "ms_per_load_step_median": 1e3 * float(np.median(seconds)),
        "ms_per_iteration": 1e3 * (time.perf_counter() - t0) / n,
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", required=True)
    p.add_argument("--data-seconds", type=float, default=360.0, help="FEM data time (a 10-minute build's share)")
    p.add_argument("--ranks", type=int, nargs="*", default=[16, 32, 64])
    p.add_argument("--full", type=int, nargs="*", default=[], help="ranks also solved unreduced (slow)")
    p.add_argument("--projection-ranks", type=int, nargs="*", default=[], help="ranks whose projection alone is scored")
    p.add_argument("--network-minutes", type=float, default=None, help="also a timed network build")
    p.add_argument("--data", default=None, help="where the data folders go (default: a temporary one)")
    p.add_argument("--out", default=None, help="write the figures here (JSON)")
    args = p.parse_args()
    limit_threads(1)
    scene = load_scene(args.scene)
    stamp, load0 = describe(), os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.data or tmp)
        test = test_set(scene, 40, root / "test", workers=2)
        test_folder = next((root / "test").glob(f"{scene.name}-*"))
        F, U, paths = load_dataset(test_folder, sorted(i for i in done_indices(test_folder) if i < 40))
        t0 = time.perf_counter()
        train_folder = training_data(scene, args.data_seconds, root)
        data_s = time.perf_counter() - t0
        mesh, loaded = scene.build_mesh()
        region = scene.region_nodes(mesh, loaded)
        material = NeoHookean.of(scene.material)
        free = mesh.free_dofs
        _, Utr, _ = load_dataset(train_folder)
        Y = U.reshape(len(U), -1)[:, free].T.astype(np.float64)
        t0 = time.perf_counter()
        W = np.linalg.svd(Utr.reshape(len(Utr), -1)[:, free].T.astype(np.float64), full_matrices=False)[0]
        svd_s = time.perf_counter() - t0
        out: dict = {"machine": stamp, "scene": scene.name, "load_before": load0, "train_samples": len(Utr),
                     "test_samples": len(U), "data_s": data_s, "svd_s": svd_s, "ranks": {}}  # fmt: skip
        out["projection"] = {
            str(r): float(
                np.median(np.linalg.norm(W[:, :r] @ (W[:, :r].T @ Y) - Y, axis=0) / np.linalg.norm(Y, axis=0))
            )
            for r in args.projection_ranks
        }
        snaps = np.random.default_rng(0).choice(len(Utr), size=min(ECSW_SNAPSHOTS, len(Utr)), replace=False)
        for r in args.ranks:
            V = W[:, :r]
            proj = np.linalg.norm(V @ (V.T @ Y) - Y, axis=0) / np.linalg.norm(Y, axis=0)
            row: dict = {"projection_mean": float(proj.mean()), "projection_median": float(np.median(proj))}
            t0 = time.perf_counter()
            G = np.concatenate([element_forces(mesh, material, Utr[j].astype(np.float64), V).T for j in snaps])
            elems, w = ecsw(G, G.sum(axis=1), ECSW_TOL)
            row.update(ecsw_s=time.perf_counter() - t0, elements=int(elems.size), tets=len(mesh.tets))
            row["reduced"] = score_rom(ReducedModel(mesh, material, V, elems, w), mesh, region, F, Y, paths)
            if r in args.full:
                every = np.arange(len(mesh.tets))
                row["unreduced"] = score_rom(ReducedModel(mesh, material, V, every, np.ones(every.size)),
                                             mesh, region, F, Y, paths)  # fmt: skip
            out["ranks"][str(r)] = row
            print(f"r={r}: {json.dumps(row)}", flush=True)
        if args.network_minutes:
            out["network"] = timed_build(scene, args.network_minutes, test, workers=2)
            print(f"network: {json.dumps(out['network'])}", flush=True)
    out["load_after"] = os.getloadavg()[0]
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

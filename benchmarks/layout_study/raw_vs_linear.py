"""Side by side on one data set: where does the whole-surface surrogate's error come from?"""

import dataclasses
import json
import sys
import time

import numpy as np

from service.build import data_key, default_data_root, load_spec
from service.fem.assembly import Assembler
from service.fem.linsolve import make_solver
from service.fem.material import NeoHookean
from service.scene import load_scene
from service.surrogate.basis import pod_basis
from service.surrogate.data import done_indices, generate, load_dataset
from service.surrogate.train import TrainConfig, split_paths, train


def main():
    scene = load_scene(sys.argv[1])
    gen_s = float(sys.argv[2])
    train_s = float(sys.argv[3])
    mesh, loaded = scene.build_mesh()
    region = scene.region_nodes(mesh, loaded)
    mat = NeoHookean.of(scene.material)
    spec = load_spec(scene, mesh, loaded)
    data_dir = default_data_root() / f"{scene.name}-{data_key(mesh.hash, mat, spec)}"
    print("nodes", mesh.n_nodes, "region", len(region), data_dir, flush=True)
    t0 = time.perf_counter()
    if gen_s > 0:
        g = generate(mesh, mat, spec, data_dir, 100000, workers=2, progress=False)
        for _ in g:
            if time.perf_counter() - t0 > gen_s:
                g.close()
                break
    done = sorted(done_indices(data_dir))
    F, U, P = load_dataset(data_dir, done)
    print("samples", len(F), "paths", len(done), "gen s", round(time.perf_counter() - t0), flush=True)
    asm = Assembler(mesh, mat)
    K = asm.stiffness_at_rest()
    solver = make_solver(K)
    solver.factor(K)
    N = len(F)
    n = mesh.n_nodes
    rhs = np.zeros((N, 3 * n))
    rr = 3 * np.repeat(region, 3) + np.tile(np.arange(3), len(region))
    rhs[:, rr] = F.reshape(N, -1)
    L = np.zeros((N, 3 * n))
    L[:, mesh.free_dofs] = solver.solve(rhs[:, mesh.free_dofs].T).T
    Uf = U.reshape(N, -1).astype(np.float64)
    tr_p, va_p = split_paths(P, 0.1, 0)
    tr = np.isin(P, tr_p)
    va = np.isin(P, va_p)

    def mm(E):
        return float(np.linalg.norm(E.reshape(len(E), -1, 3), axis=-1).mean() * 1e3)

    res = {"samples": N, "zero_mm": mm(Uf[va]), "linear_mm": mm(Uf[va] - L[va])}
    R = Uf - L
    for r in (128, 256, 512):
        B, _ = pod_basis(Uf[tr], r)
        res[f"pod_U_{r}"] = mm(Uf[va] - (Uf[va] @ B) @ B.T)
        B, _ = pod_basis(R[tr], r)
        res[f"pod_rem_{r}"] = mm(R[va] - (R[va] @ B) @ B.T)
    print(json.dumps(res), flush=True)
    if train_s > 0:
        base = TrainConfig(members=1, max_seconds=train_s, epochs=400, patience=60)
        for name, cfg, target in [
            ("skip_in_basis", dataclasses.replace(base, physics_skip=True), Uf),
            ("full_linear+rem", base, R),
        ]:
            out = train(F, target.reshape(N, n, 3).astype(np.float32), P, asm, region, cfg, progress=False)
            res[name] = out.metrics["mean_mm"]
            res[name + "_epochs"] = out.metrics["epochs"]
            print(name, json.dumps(out.metrics), flush=True)
    print(json.dumps(res))


if __name__ == "__main__":
    main()

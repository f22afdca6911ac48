"""Remainder network fed by the linear response's POD coefficients instead of raw forces."""

import json
import sys
import time

import numpy as np
import torch

from service.build import data_key, default_data_root, load_spec
from service.fem.assembly import Assembler
from service.fem.linsolve import make_solver
from service.fem.material import NeoHookean
from service.scene import load_scene
from service.surrogate.basis import pod_basis
from service.surrogate.data import done_indices, load_dataset
from service.surrogate.network import mlp
from service.surrogate.train import split_paths


def main():
    scene = load_scene(sys.argv[1])
    secs = float(sys.argv[2])
    mesh, loaded = scene.build_mesh()
    region = scene.region_nodes(mesh, loaded)
    mat = NeoHookean.of(scene.material)
    spec = load_spec(scene, mesh, loaded)
    data_dir = default_data_root() / f"{scene.name}-{data_key(mesh.hash, mat, spec)}"
    F, U, P = load_dataset(data_dir, sorted(done_indices(data_dir)))
    asm = Assembler(mesh, mat)
    K = asm.stiffness_at_rest()
    s = make_solver(K)
    s.factor(K)
    N, n = len(F), mesh.n_nodes
    rhs = np.zeros((N, 3 * n))
    rr = 3 * np.repeat(region, 3) + np.tile(np.arange(3), len(region))
    rhs[:, rr] = F.reshape(N, -1)
    L = np.zeros((N, 3 * n))
    L[:, mesh.free_dofs] = s.solve(rhs[:, mesh.free_dofs].T).T
    Uf = U.reshape(N, -1).astype(np.float64)
    R = Uf - L
    trp, vap = split_paths(P, 0.1, 0)
    tr = np.isin(P, trp)
    va = np.isin(P, vap)

    def mm(E):
        return float(np.linalg.norm(E.reshape(len(E), -1, 3), axis=-1).mean() * 1e3)

    out = {"N": N, "linear": mm(R[va])}
    for rin, rout, hidden, wd in [
        (int(a), int(b), [int(h) for h in c.split("x")], float(d))
        for a, b, c, d in (x.split(",") for x in sys.argv[3:])
    ]:
        Bi, _ = pod_basis(L[tr], rin)
        Bo, _ = pod_basis(R[tr], rout)
        X = L @ Bi
        Y = R @ Bo
        xs, ys = X[tr].std(0).mean() + 1e-30, np.sqrt((Y[tr] ** 2).mean()) + 1e-30
        Xt = torch.tensor(X / xs, dtype=torch.float32)
        Yt = torch.tensor(Y / ys, dtype=torch.float32)
        torch.manual_seed(0)
        net = mlp(rin, hidden, rout)
        opt = torch.optim.Adam(net.parameters(), lr=1e-3, weight_decay=wd)
        itr = np.flatnonzero(tr)
        best = (mm(R[va]), 0)
        t0 = time.perf_counter()
        ep = 0
        while time.perf_counter() - t0 < secs:
            perm = np.random.default_rng(ep).permutation(itr)
            for i in range(0, len(perm), 128):
                b = perm[i : i + 128]
                loss = ((net(Xt[b]) - Yt[b]) ** 2).sum(1).mean()
                opt.zero_grad()
                loss.backward()
                opt.step()
            ep += 1
            with torch.no_grad():
                pred = net(Xt[va]).numpy().astype(np.float64) * ys @ Bo.T
            e = mm(R[va] - pred)
            if e < best[0]:
                best = (e, ep)
        out[f"in{rin}_out{rout}_{'x'.join(map(str, hidden))}_wd{wd}"] = (round(best[0], 4), best[1], ep)
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()

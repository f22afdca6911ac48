"""FEM benchmark (the paper's liver): Newton from rest and warm-started, time per iteration,
and the sparse factorisations side by side."""

from __future__ import annotations

import logging
import time

import numpy as np

from ..fem.assembly import Assembler
from ..fem.linsolve import available_backends, make_solver
from ..fem.material import NeoHookean
from ..fem.newton import NewtonOptions, NewtonSolver
from ..mesh import TetMesh
from .cases import Case

log = logging.getLogger(__name__)


def _median_time(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def paper_like_loads(mesh: TetMesh, support: np.ndarray, rng: np.random.Generator, n: int = 4) -> list[np.ndarray]:
    """Outward pulls of 1 to 4 N on patches of 20-35 surface nodes around the tool's area."""
    loads = []
    for _ in range(n):
        centre = int(rng.choice(support))
        patch = mesh.surface_patch(centre, int(rng.integers(20, 36)))
        normal = mesh.patch_normal(patch)
        g = np.zeros((mesh.n_nodes, 3))
        g[patch] = normal * rng.uniform(1.0, 4.0) / patch.size
        loads.append(g)
    return loads


def solver_comparison(asm: Assembler, u: np.ndarray, repeats: int = 3) -> list[dict]:
    """Numeric factorisation and solve times of each available backend on the tangent at u."""
    K = asm.tangent(u)
    b = np.random.default_rng(0).normal(size=K.shape[0])
    rows = []
    for name in available_backends():
        t0 = time.perf_counter()
        solver = make_solver(K, name)
        setup = time.perf_counter() - t0
        factor, _ = _median_time(lambda solver=solver: solver.factor(K), repeats)
        solve, x = _median_time(lambda solver=solver: solver.solve(b), repeats)
        rows.append({
            "backend": name,
            "analysis_ms": 1e3 * setup,
            "factor_ms": 1e3 * factor,
            "solve_ms": 1e3 * solve,
            "residual": float(np.linalg.norm(K @ x - b) / np.linalg.norm(b)),
        })  # fmt: skip
    return rows


def newton_benchmark(case: Case, material: NeoHookean, tool: np.ndarray, repeats: int = 3, seed: int = 0) -> dict:
    """Newton on the liver: the sequence's largest load and paper-like patches from rest, the
    recorded sequence warm-started frame to frame, per backend."""
    mesh = case.mesh
    asm = Assembler(mesh, material)
    rng = np.random.default_rng(seed)
    largest = int(np.argmax(np.linalg.norm(case.net_forces, axis=1)))
    g_seq = np.zeros((case.frames, mesh.n_nodes, 3))
    g_seq[:, tool] = case.net_forces[:, None, :] / tool.size
    extra = paper_like_loads(mesh, case.support, rng)
    out = {"backends": {}}
    for name in available_backends():
        solver = NewtonSolver(asm, NewtonOptions(backend=name))
        cold, res = _median_time(lambda solver=solver: solver.solve(g_seq[largest]), repeats)
        per_it = cold / max(res.iterations, 1)
        patches = []
        for g in extra:
            r = solver.solve(g)
            patches.append({"seconds": r.seconds, "iterations": r.iterations, "converged": r.converged,
                            "max_displacement_mm": float(np.linalg.norm(r.u, axis=1).max() * 1e3),
                            "force_N": float(np.linalg.norm(g.sum(0)))})  # fmt: skip
        u, warm, its, err = None, [], [], 0.0
        for k in range(case.frames):
            r = solver.solve(g_seq[k], u)
            u = r.u
            warm.append(r.seconds)
            its.append(r.iterations)
            err = max(err, float(np.linalg.norm(mesh.nodes + u - case.positions[k], axis=1).max()))
        out["backends"][name] = {
            "largest_from_rest_s": cold,
            "largest_iterations": res.iterations,
            "largest_max_displacement_mm": float(np.linalg.norm(res.u, axis=1).max() * 1e3),
            "per_iteration_ms": 1e3 * per_it,
            "patches_from_rest": patches,
            "warm_frame_median_s": float(np.median(warm[1:])),
            "warm_iterations_median": float(np.median(its[1:])),
            "sequence_max_error_mm": 1e3 * err,
        }
        log.info("newton %s: largest from rest %.2f s, warm %.3f s", name, cold, np.median(warm[1:]))
    out["solvers"] = solver_comparison(asm, case.positions[largest] - mesh.nodes, repeats)
    return out

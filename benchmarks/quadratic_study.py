"""Quadratic tets against refined linear ones: how near each comes to the converged liver.

The any-site force error is mostly the coarse P1 mesh's stiffness (locking_study.py: 1.27-1.56x
its refinement at nu = 0.49, and that refinement 1.17-1.26x its own). This asks whether
quadratic (P2, ten-node) tets on the scene's own mesh would close the gap: small-strain
elasticity (the Neo-Hookean law's linearisation at rest), one load per calibration site, the
same continuum load for every discretisation: a uniform traction of 1 N along the patch's
outward normal over the coarse surface triangles whose three nodes lie in the tool patch, each
discretisation's consistent nodal load of it. Compliance c = f . u is then monotone under
refinement of a conforming space (P1 on the mesh subdivided once and twice; P2 on the coarse
mesh holds P1 on it), and c_converged / c_h is the factor by which a method exact on that
discretisation overestimates a force. The last level's gap is extrapolated geometrically from
the three P1 levels (Richardson with the observed rate).

    python benchmarks/quadratic_study.py --scene benchmarks/scenes/liver_paper.toml --nu 0.49 0.3
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from locking_study import outward, scene_entry, tools

from service.bench.anysite import CALIBRATION_SEED
from service.bench.machine import describe
from service.bench.truth import face_midpoints, subdivide
from service.config import limit_threads
from service.fem.linsolve import make_solver
from service.fem.quadratic import QuadraticAssembler
from service.fem.rest import RestCompliance
from service.mesh import TetMesh

Array = np.ndarray


def patch_test(constrained: QuadraticAssembler) -> dict:
    """The element's own checks on this mesh, nothing fixed: a linear field's energy is exact,
    rigid motions cost nothing."""
    elements, nodes = constrained.elements, constrained.nodes
    free = TetMesh(elements.nodes, elements.tets), TetMesh(nodes.nodes, nodes.tets)
    asm = QuadraticAssembler(*free, constrained.material)
    K = asm.stiffness_at_rest()
    x = asm.nodes.nodes
    A = np.array([[1.0, 2.0, 0.0], [0.0, -1.0, 3.0], [1.0, 0.0, 2.0]]) * 1e-3
    eps = 0.5 * (A + A.T)
    mat = asm.material
    exact = (0.5 * mat.lam * np.trace(eps) ** 2 + mat.mu * (eps * eps).sum()) * asm.elements.volumes.sum()
    u = asm.pack(x @ A.T)
    skew = np.array([[0.0, 1.0, 2.0], [-1.0, 0.0, 3.0], [-2.0, -3.0, 0.0]]) * 1e-3
    rigid = asm.pack(x @ skew.T + [1e-3, 2e-3, 3e-3])
    return {
        "linear_field_energy_ratio": float(0.5 * u @ K @ u / exact),
        "rigid_force_over_linear": float(np.abs(K @ rigid).max() / np.abs(K @ u).max()),
    }


def traction_triangles(coarse, patch: Array) -> Array:
    """The coarse surface triangles whose three nodes lie in the patch: the loaded area."""
    inside = np.zeros(coarse.n_nodes, bool)
    inside[patch] = True
    faces = coarse.surface_faces
    return faces[inside[faces].all(axis=1)]


def p1_load(mesh, loaded: Array, normal: Array, n_total: int) -> Array:
    """Consistent P1 load of a unit traction resultant over `loaded` triangles (node ids of `mesh`):
    each triangle's share of the force to its three nodes in thirds."""
    x = mesh.nodes[loaded]
    area = 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)
    f = np.zeros((n_total, 3))
    np.add.at(f, loaded.ravel(), np.repeat(area / 3.0, 3)[:, None] * normal)
    return (f / area.sum()).ravel()


def p2_load(coarse, loaded: Array, normal: Array, n_total: int) -> Array:
    """The same traction's consistent load on six-node triangles: nothing at the corners, a
    third of each triangle's force at each of its edge midpoints."""
    x = coarse.nodes[loaded]
    area = 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)
    mids = refine_faces(loaded, coarse)[-len(loaded) :]  # the centre triangles: the three midpoints
    f = np.zeros((n_total, 3))
    np.add.at(f, mids.ravel(), np.repeat(area / 3.0, 3)[:, None] * normal)
    return (f / area.sum()).ravel()


def refine_faces(faces: Array, mesh) -> Array:
    """Each triangle of `mesh` into four at its edge midpoints, numbered as subdivide() does."""
    a, b, c = faces.T
    ab, bc, ca = face_midpoints(mesh, faces).T
    return np.concatenate([np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])


def compliance_p2(asm: QuadraticAssembler, loads: list[Array]) -> list[float]:
    """c = f . u on ten-node tets of the coarse mesh; its nodes are the once-subdivided mesh's."""
    K = asm.stiffness_at_rest()
    solver = make_solver(K)
    solver.factor(K)
    return [float(asm.pack(f) @ solver.solve(asm.pack(f))) for f in loads]


def study(scene: str, nu: float, finest: int) -> list[dict]:
    entry = scene_entry(scene, nu)
    coarse, material = entry.mesh, entry.fem.material
    meshes = [coarse]
    for _ in range(finest):
        meshes.append(subdivide(meshes[-1]))
    sites = tools(entry, 4, CALIBRATION_SEED)
    rows = [{"nu": nu, "site": site, "normal": outward(coarse, tool).tolist()} for site, tool in sites]
    faces = [traction_triangles(coarse, tool) for _, tool in sites]
    for row, tri in zip(rows, faces, strict=True):
        row["loaded_triangles"] = int(len(tri))
    for level, mesh in enumerate(meshes):
        t0 = time.perf_counter()
        compliance = RestCompliance(mesh, material)  # not the cache: 8 GB at level 2
        for row, tri in zip(rows, faces, strict=True):
            level_tri = tri
            for k in range(level):
                level_tri = refine_faces(level_tri, meshes[k])
            f = p1_load(mesh, level_tri, np.asarray(row["normal"]), mesh.n_nodes)
            row[f"c_p1_l{level}"] = float(f @ compliance.solve(f))
        print(f"nu {nu}: P1 level {level} ({mesh.n_nodes} nodes) {time.perf_counter() - t0:.1f} s", flush=True)
        del compliance
    t0 = time.perf_counter()
    fine = meshes[1]
    normals = [np.asarray(row["normal"]) for row in rows]
    loads = [p2_load(coarse, tri, n, fine.n_nodes) for n, tri in zip(normals, faces, strict=True)]
    asm = QuadraticAssembler(coarse, fine, material)
    check = patch_test(asm)
    assert abs(check["linear_field_energy_ratio"] - 1) < 1e-9 and check["rigid_force_over_linear"] < 1e-9, check
    for row in rows:
        row["p2_patch_test"] = check
    for row, c_p2 in zip(rows, compliance_p2(asm, loads), strict=True):
        row["c_p2_l0"] = c_p2
    print(f"nu {nu}: P2 level 0 ({fine.n_nodes} nodes) {time.perf_counter() - t0:.1f} s", flush=True)
    for row in rows:
        c = [row[f"c_p1_l{k}"] for k in range(finest + 1)]
        if finest >= 2:
            rate = (c[2] - c[1]) / (c[1] - c[0])  # the gap shrinks by this factor a level
            row["rate"] = rate
            row["c_extrapolated"] = c[2] + (c[2] - c[1]) * rate / (1 - rate) if 0 < rate < 1 else None
    return rows


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default=str(ROOT / "benchmarks" / "scenes" / "liver_paper.toml"))
    p.add_argument("--nu", type=float, nargs="+", default=[0.49, 0.3])
    p.add_argument("--finest", type=int, default=2, help="P1 subdivision levels (2: 71 s and 8 GB on the liver)")
    p.add_argument("--out", default=str(ROOT / "reports" / "quadratic" / "quadratic_study.json"))
    args = p.parse_args()
    limit_threads(1)
    result: dict = {"machine": describe(), "scene": args.scene, "seed": CALIBRATION_SEED, "rows": []}
    for nu in args.nu:
        result["rows"] += study(args.scene, nu, args.finest)
    for r in result["rows"]:  # compliance over the coarse P1 mesh's: its stiffness bias
        over = {k: round(v / r["c_p1_l0"], 3) for k, v in r.items() if k.startswith("c_") and v is not None}
        print(f"nu {r['nu']}, site {r['site']}: compliance / coarse P1 {over}", flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Ten-node tets: forces and tangent against finite differences, the patch test, rigid motions,
and more compliance than linear tets on the same mesh (their space holds the linear one)."""

import numpy as np
import pytest

from service.bench.truth import subdivide
from service.fem.assembly import Assembler
from service.fem.material import NeoHookean
from service.fem.newton import NewtonSolver
from service.fem.quadratic import QuadraticAssembler, QuadraticFEM
from service.mesh import TetMesh


def quadratic(mesh: TetMesh, material: NeoHookean) -> QuadraticAssembler:
    return QuadraticAssembler(mesh, subdivide(mesh), material)


def displaced(asm: QuadraticAssembler, scale: float, seed: int) -> np.ndarray:
    u = np.random.default_rng(seed).normal(size=(asm.nodes.n_nodes, 3)) * scale
    return asm.unpack(asm.pack(u))


def test_internal_force_is_energy_gradient_and_tangent_its_gradient(cube):
    asm = quadratic(cube, NeoHookean(4500.0, 0.45))
    u = displaced(asm, 0.02, seed=0)
    x = asm.pack(u)
    f = asm.pack(asm.internal_force(u))
    K = asm.tangent(u).toarray()
    h = 1e-7
    rng = np.random.default_rng(1)
    for _ in range(5):  # directional derivatives: energy -> force, force -> tangent
        d = rng.normal(size=x.size)
        e_plus, e_minus = asm.energy(asm.unpack(x + h * d)), asm.energy(asm.unpack(x - h * d))
        assert (e_plus - e_minus) / (2 * h) == pytest.approx(f @ d, rel=1e-6)
        fp = asm.pack(asm.internal_force(asm.unpack(x + h * d)))
        fm = asm.pack(asm.internal_force(asm.unpack(x - h * d)))
        np.testing.assert_allclose((fp - fm) / (2 * h), K @ d, atol=1e-6 * np.abs(K @ d).max())
    np.testing.assert_allclose(K, K.T, atol=1e-10 * np.abs(K).max())


def test_homogeneous_stretch_patch_and_rigid_motion(bar):
    """A homogeneous deformation leaves interior nodes without net force and the end face with
    P0 N times its area; a rigid motion stores nothing."""
    free = TetMesh(bar.nodes, bar.tets)
    asm = QuadraticAssembler(free, subdivide(free), NeoHookean(4500.0, 0.3))
    X = asm.nodes.nodes
    F0 = np.diag([1.3, 0.9, 0.95])
    F0[0, 1] = 0.1
    f = asm.internal_force(X @ (F0 - np.eye(3)).T)
    interior = np.setdiff1d(np.arange(asm.nodes.n_nodes), asm.nodes.surface_nodes)
    np.testing.assert_allclose(f[interior], 0.0, atol=1e-10 * asm.material.E)
    mat = asm.material
    Finvt = np.linalg.inv(F0).T
    P0 = mat.mu * (F0 - Finvt) + mat.lam * np.log(np.linalg.det(F0)) * Finvt
    end = X[:, 0] == X[:, 0].max()
    np.testing.assert_allclose(f[end].sum(0), P0 @ np.array([1.0, 0, 0]), rtol=1e-10, atol=1e-10 * mat.E)
    Q, _ = np.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))
    Q *= np.sign(np.linalg.det(Q))
    rigid = X @ Q.T + [0.1, -0.2, 0.3] - X
    assert abs(asm.energy(rigid)) < 1e-9 * mat.E * free.volumes.sum()
    np.testing.assert_allclose(asm.internal_force(rigid), 0.0, atol=1e-9 * mat.E)


def test_quadratic_tets_are_softer_than_linear_ones_on_the_same_mesh(bar):
    """A load on corner nodes does the same work on a linear field either way, and the quadratic
    space holds the linear one, so its compliance f . u can only be larger; near-incompressible,
    much larger (linear tets lock)."""
    mat = NeoHookean(4500.0, 0.49)
    p1, p2 = Assembler(bar, mat), quadratic(bar, mat)
    tip = np.flatnonzero(bar.nodes[:, 0] == bar.nodes[:, 0].max())
    f1 = np.zeros((bar.n_nodes, 3))
    f1[tip, 2] = -1e-3
    f2 = np.zeros((p2.nodes.n_nodes, 3))
    f2[tip, 2] = -1e-3
    c1 = p1.pack(f1) @ np.linalg.solve(p1.stiffness_at_rest().toarray(), p1.pack(f1))
    c2 = p2.pack(f2) @ np.linalg.solve(p2.stiffness_at_rest().toarray(), p2.pack(f2))
    assert c2 > 1.5 * c1


def test_newton_on_quadratic_tets_matches_their_linear_response_at_small_load(bar):
    mat = NeoHookean(4500.0, 0.45)
    model = QuadraticFEM(subdivide(bar), mat, elements=bar)
    asm = model.assembler
    tip = np.flatnonzero(bar.nodes[:, 0] == bar.nodes[:, 0].max())
    g = np.zeros((model.mesh.n_nodes, 3))
    g[tip, 2] = -1e-3  # strains of 1e-5: the linear response
    linear = asm.unpack(np.linalg.solve(asm.stiffness_at_rest().toarray(), asm.pack(g)))
    res = NewtonSolver(asm).solve(g)
    assert res.converged
    np.testing.assert_allclose(res.u, linear, atol=1e-3 * np.abs(linear).max())
    big = NewtonSolver(asm).solve(g * 300)  # 15 cm at the tip of a 4 m bar: nonlinear
    assert big.converged
    assert np.abs(big.u - 300 * linear).max() > 1e-2 * np.abs(big.u).max()


def test_quadratic_model_refuses_what_it_cannot_do(bar):
    with pytest.raises(ValueError, match="subdivided once"):
        QuadraticAssembler(bar, bar, NeoHookean(4500.0, 0.45))
    tip = np.flatnonzero(bar.nodes[:, 0] == bar.nodes[:, 0].max())[:3]
    op = QuadraticFEM(subdivide(bar), NeoHookean(4500.0, 0.45), elements=bar).restrict(tip)
    with pytest.raises(NotImplementedError, match="equilibria only"):
        op(np.zeros((3, 3)))

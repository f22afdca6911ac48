"""Vectorised assembly: forces and tangent against finite differences, rigid invariance, and
a homogeneous-stress patch check against the analytical Neo-Hookean stress."""

import os

import numpy as np
import pytest

from service.fem.assembly import Assembler, generic_element_stiffness
from service.fem.kernels import compiled as _kernels
from service.fem.material import NeoHookean
from service.mesh import TetMesh


def displaced(mesh: TetMesh, scale: float, seed: int = 0) -> np.ndarray:
    u = np.random.default_rng(seed).normal(size=(mesh.n_nodes, 3)) * scale
    u[mesh.fixed] = 0.0
    return u


def test_internal_force_is_energy_gradient(cube):
    asm = Assembler(cube, NeoHookean(4500.0, 0.45))
    u = displaced(cube, 0.04)
    f = asm.internal_force(u)
    h = 1e-7
    fd = np.zeros_like(u)
    for a in range(cube.n_nodes):
        for i in range(3):
            e = np.zeros_like(u)
            e[a, i] = h
            fd[a, i] = (asm.energy(u + e) - asm.energy(u - e)) / (2 * h)
    np.testing.assert_allclose(f, fd, atol=1e-6 * np.abs(f).max())


def test_tangent_is_force_gradient(cube):
    asm = Assembler(cube, NeoHookean(4500.0, 0.45))
    u = displaced(cube, 0.04, seed=1)
    K = asm.tangent(u).toarray()
    x = asm.pack(u)
    h = 1e-7
    fd = np.empty_like(K)
    for j in range(x.size):
        e = np.zeros_like(x)
        e[j] = h
        fp = asm.pack(asm.internal_force(asm.unpack(x + e)))
        fm = asm.pack(asm.internal_force(asm.unpack(x - e)))
        fd[:, j] = (fp - fm) / (2 * h)
    np.testing.assert_allclose(K, fd, atol=1e-6 * np.abs(K).max())
    np.testing.assert_allclose(K, K.T, atol=1e-10 * np.abs(K).max())


def test_structured_stiffness_equals_generic_contraction(bar):
    asm = Assembler(bar, NeoHookean(4500.0, 0.49))
    F = asm.F(displaced(bar, 0.05, seed=2))
    generic = generic_element_stiffness(asm.material.tangent(F), bar.shape_gradients, bar.volumes)
    structured = asm.element_stiffness(F)
    np.testing.assert_allclose(structured, generic, atol=1e-10 * np.abs(generic).max())


def test_rigid_motion_stores_no_energy(bar):
    mesh = TetMesh(bar.nodes, bar.tets)  # no fixed nodes: rigid motions allowed
    asm = Assembler(mesh, NeoHookean(4500.0, 0.49))
    rng = np.random.default_rng(3)
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    Q *= np.sign(np.linalg.det(Q))
    u = mesh.nodes @ Q.T + rng.normal(size=3) - mesh.nodes
    assert abs(asm.energy(u)) < 1e-9 * asm.material.E * mesh.volumes.sum()
    np.testing.assert_allclose(asm.internal_force(u), 0.0, atol=1e-9 * asm.material.E)


def test_homogeneous_stretch_patch(bar):
    """Under u = (F0 - I) X the stress is uniform: interior nodes carry no net force and the
    end face carries P0 N times its area, with P0 the analytical Neo-Hookean stress."""
    mat = NeoHookean(4500.0, 0.3)
    asm = Assembler(TetMesh(bar.nodes, bar.tets), mat)
    F0 = np.diag([1.3, 0.9, 0.95])
    F0[0, 1] = 0.1
    u = bar.nodes @ (F0 - np.eye(3)).T
    f = asm.internal_force(u)
    interior = np.setdiff1d(np.arange(bar.n_nodes), bar.surface_nodes)
    np.testing.assert_allclose(f[interior], 0.0, atol=1e-10 * mat.E)
    J = np.linalg.det(F0)
    Finvt = np.linalg.inv(F0).T
    P0 = mat.mu * (F0 - Finvt) + mat.lam * np.log(J) * Finvt
    end = bar.nodes[:, 0] == bar.nodes[:, 0].max()
    area = 1.0  # the bar's 1 x 1 end face
    np.testing.assert_allclose(f[end].sum(0), P0 @ np.array([1.0, 0, 0]) * area, rtol=1e-10)


def test_compiled_kernels_equal_the_numpy_reference(bar):
    import pytest

    pytest.importorskip("numba")
    mat = NeoHookean(4500.0, 0.49)
    fast, ref = Assembler(bar, mat, compiled=True), Assembler(bar, mat, compiled=False)
    u = displaced(bar, 0.05, seed=4)
    assert fast.energy(u) == np.float64(ref.energy(u)) or np.isclose(fast.energy(u), ref.energy(u), rtol=1e-12)
    np.testing.assert_allclose(fast.internal_force(u), ref.internal_force(u), atol=1e-11 * mat.E)
    np.testing.assert_allclose(fast.tangent(u).toarray(), ref.tangent(u).toarray(), atol=1e-11 * mat.E)
    crushed = u.copy()
    crushed[bar.free_mask] = -bar.nodes[bar.free_mask] * 2.0  # inverts elements
    assert np.isinf(fast.energy(crushed)) and np.isinf(ref.energy(crushed))


def test_a_singular_element_gives_non_finite_forces_in_both_paths(bar):
    """A field that collapses the free nodes onto the origin (det F = 0: a network's answer to a
    1e30 N load cancels to it) is non-finite forces, as NumPy's are: not numba's ZeroDivisionError."""
    pytest.importorskip("numba")
    mat = NeoHookean(4500.0, 0.49)
    collapsed = np.zeros_like(bar.nodes)
    collapsed[bar.free_mask] = -bar.nodes[bar.free_mask]
    with np.errstate(divide="ignore", invalid="ignore"):
        for compiled in (True, False):
            asm = Assembler(bar, mat, compiled=compiled)
            assert not np.isfinite(asm.internal_force(collapsed)).all(), compiled


@pytest.mark.parametrize("compiled", [True, False])
def test_the_energy_resolves_a_small_loads_change(bar, compiled):
    """Near rest the energy's change along a tiny step is the internal force's work on it, to
    1e-6: J - 1 and tr C - 3 come from grad u's invariants, not as differences of numbers near
    1, whose rounding (eps a tet) once exceeded a small load's whole change of energy, so that
    Newton's line search rejected good steps."""
    if compiled and _kernels() is None:
        pytest.skip("numba is not importable")
    asm = Assembler(bar, NeoHookean(4500.0, 0.49), compiled)
    rng = np.random.default_rng(0)
    free = np.ones((bar.n_nodes, 1))
    free[bar.fixed] = 0.0
    u = rng.normal(size=(bar.n_nodes, 3)) * 1e-7 * free
    d = rng.normal(size=(bar.n_nodes, 3)) * 1e-9 * free
    change = asm.energy(u + d) - asm.energy(u - d)  # central: 2 f.d + O(|d|^3)
    work = 2.0 * float((asm.internal_force(u) * d).sum())
    assert change == pytest.approx(work, rel=1e-6, abs=0.0)  # approx alone allows 1e-12


def test_an_assembly_split_over_two_cores_gives_the_same_digits(bar, monkeypatch):
    """A frame with a spare core assembles half the tets there; the compiled kernels always sum
    two halves, so the tangent and the internal force are the same to the last digit whether
    the half ran beside or inline (an answer must not depend on the server's load)."""
    pytest.importorskip("numba")
    import service.fem.assembly as assembly
    from service import spare

    asm = Assembler(bar, NeoHookean(4500.0, 0.49), compiled=True)
    u = displaced(bar, 0.05, seed=5)
    inline = asm.tangent(u).data.copy(), asm.internal_force(u)
    monkeypatch.setattr(assembly, "BESIDE_MIN_TETS", 0)  # the bar is small: split it anyway
    ran_on = []
    real = assembly.Beside

    def watched(fn, start=None):
        ran_on.append(start)
        return real(fn, start)

    monkeypatch.setattr(assembly, "Beside", watched)
    with spare.frame():
        beside = asm.tangent(u).data, asm.internal_force(u)
    assert ran_on == [(os.cpu_count() or 1) > 1] * 2  # handed beside where a core is spare
    assert np.array_equal(beside[0], inline[0]) and np.array_equal(beside[1], inline[1])
    ref = Assembler(bar, NeoHookean(4500.0, 0.49), compiled=False)
    np.testing.assert_allclose(beside[1], ref.internal_force(u), atol=1e-11 * 4500.0)

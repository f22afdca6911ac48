"""Newton's method: exact answers, the linear limit, scaling, hard cases, failure as a result."""

import time

import numpy as np
import pytest

from service.fem.assembly import Assembler
from service.fem.material import NeoHookean
from service.fem.newton import NewtonOptions, NewtonSolver


def tip_load(mesh, total) -> np.ndarray:
    """`total` (3,) spread evenly over the nodes of the free end (x = max)."""
    g = np.zeros((mesh.n_nodes, 3))
    end = np.flatnonzero(mesh.nodes[:, 0] == mesh.nodes[:, 0].max())
    g[end] = np.asarray(total) / end.size
    return g


def end_face_load(mesh, traction: np.ndarray) -> np.ndarray:
    """Consistent nodal forces of a uniform traction on the end face (a third of each area)."""
    x = mesh.nodes
    faces = mesh.surface_faces[(x[mesh.surface_faces, 0] == x[:, 0].max()).all(axis=1)]
    area = 0.5 * np.linalg.norm(np.cross(x[faces[:, 1]] - x[faces[:, 0]], x[faces[:, 2]] - x[faces[:, 0]]), axis=1)
    g = np.zeros((mesh.n_nodes, 3))
    for k in range(3):
        np.add.at(g, faces[:, k], np.outer(area / 3.0, traction))
    return g


def test_zero_load_gives_rest(bar):
    res = NewtonSolver(Assembler(bar, NeoHookean(4500.0, 0.49))).solve(np.zeros((bar.n_nodes, 3)))
    assert res.converged and res.iterations == 0
    assert not res.u.any()


def test_uniaxial_stretch_matches_analytical_solution(bar):
    """nu = 0: uniaxial stress has no lateral contraction, so the clamped bar stretches
    homogeneously; P11 = mu (s - 1/s) for a stretch s, exactly representable with P1."""
    mat = NeoHookean(4500.0, 0.0)
    s = 1.6
    g = end_face_load(bar, np.array([mat.mu * (s - 1.0 / s), 0.0, 0.0]))
    res = NewtonSolver(Assembler(bar, mat)).solve(g)
    assert res.converged
    expected = np.zeros_like(bar.nodes)
    expected[:, 0] = (s - 1.0) * bar.nodes[:, 0]
    np.testing.assert_allclose(res.u, expected, atol=1e-9)


def test_small_loads_follow_linear_elasticity(bar):
    asm = Assembler(bar, NeoHookean(4500.0, 0.45))
    solver = NewtonSolver(asm)
    K = asm.stiffness_at_rest()
    diffs = []
    for eps in (1e-2, 1e-3):
        g = tip_load(bar, [0.0, 0.0, -eps * 100.0])
        u_lin = asm.unpack(np.linalg.solve(K.toarray(), asm.pack(g)))
        u = solver.solve(g).u
        diffs.append(np.linalg.norm(u - u_lin) / np.linalg.norm(u_lin))
    assert diffs[1] < 1e-3
    assert diffs[1] == pytest.approx(diffs[0] / 10.0, rel=0.2)  # first order in the load


@pytest.mark.parametrize("nu", [0.3, 0.49, 0.499])
def test_tiny_loads_converge_to_the_linear_answer(bar, nu):
    """A load of 1e-9 to 1e-15 of the bar's (a cloud a hair off rest, or a huge alpha): the
    residual's floor is the internal forces' roundoff, far above 1e-9 of such a load, so
    Newton ran to max_iter or cut its steps to nothing. It must converge to K0^-1 g."""
    asm = Assembler(bar, NeoHookean(4500.0, nu))
    solver = NewtonSolver(asm)
    K = asm.stiffness_at_rest().toarray()
    for scale in (1e-9, 1e-12, 1e-15):
        g = tip_load(bar, [0.0, 30.0 * scale, -100.0 * scale])
        u_lin = asm.unpack(np.linalg.solve(K, asm.pack(g)))
        res = solver.solve(g)
        assert res.converged and res.iterations <= 3, (scale, res.status, res.iterations)
        np.testing.assert_allclose(res.u, u_lin, rtol=1e-6, atol=1e-6 * np.abs(u_lin).max())


@pytest.mark.parametrize("nu", [0.3, 0.49, 0.499])
def test_the_roundoff_floor_leaves_ordinary_loads_to_the_tolerance(bar, nu):
    """A load that moves the bar 1 % of its length (strains of about 1e-2): the tolerance
    decides, not the floor, so such solves are as before."""
    asm = Assembler(bar, NeoHookean(4500.0, nu))
    solver = NewtonSolver(asm)
    g = tip_load(bar, [0.0, 0.0, -1.0])
    g *= 0.04 / np.abs(solver.solve(g).u).max()
    assert np.abs(solver.solve(g).u).max() == pytest.approx(0.04, rel=0.05)
    assert solver.roundoff < NewtonOptions().rtol * np.linalg.norm(asm.pack(g))  # 0.41 of it at nu 0.499


def test_stiffer_material_and_larger_load_give_the_same_displacement(bar):
    g = tip_load(bar, [0.0, 30.0, -120.0])
    u1 = NewtonSolver(Assembler(bar, NeoHookean(4500.0, 0.49))).solve(g)
    u10 = NewtonSolver(Assembler(bar, NeoHookean(45000.0, 0.49))).solve(10.0 * g)
    assert u1.converged and u10.converged
    assert np.abs(u1.u).max() > 1.0  # a large deformation (a quarter of the length)
    np.testing.assert_allclose(u10.u, u1.u, atol=1e-8)


def test_nearly_incompressible(bar):
    res = NewtonSolver(Assembler(bar, NeoHookean(4500.0, 0.499))).solve(tip_load(bar, [0, 0, -100.0]))
    assert res.converged and np.isfinite(res.u).all()
    assert np.abs(res.u).max() > 0.3  # a tenth of the length: well past linear
    J = np.linalg.det(Assembler(bar, NeoHookean(4500.0, 0.499)).F(res.u))
    assert np.abs(J - 1).max() < 0.05


def test_crushing_load_never_produces_nan(bar):
    """A load that tries to push the tip through the bar: the solve runs out of iterations and
    says so, with a finite, uninverted state (never NaN, never an exception)."""
    g = np.zeros((bar.n_nodes, 3))
    corner = np.argmin(np.linalg.norm(bar.nodes - [4.0, 1.0, 1.0], axis=1))
    g[corner] = [-3000.0, -3000.0, -3000.0]
    res = NewtonSolver(Assembler(bar, NeoHookean(4500.0, 0.49))).solve(g)
    assert np.isfinite(res.u).all() and np.isfinite(res.residual)
    assert res.status == "max_iter" and not res.converged and res.iterations == NewtonOptions().max_iter
    assert np.abs(res.u).max() > 1.0  # it followed the load a long way before it stopped
    J = np.linalg.det(Assembler(bar, NeoHookean(4500.0, 0.49)).F(res.u))
    assert (J > 0).all()


@pytest.mark.parametrize("size", [1e7, 1e12, 1e300])
def test_an_absurd_load_ends_at_once_with_no_path(bar, size):
    """Its linear predictor asks for strains of millions (or overflows): no load step can be
    small enough, and the solve says so at once instead of creeping along for ever."""
    res = NewtonSolver(Assembler(bar, NeoHookean(4500.0, 0.49))).solve(tip_load(bar, [0.0, 0.0, -size]))
    assert not res.converged and res.status == "load_step_too_small" and res.seconds < 5.0
    assert np.isfinite(res.u).all()


def test_warm_start_needs_fewer_iterations(bar):
    solver = NewtonSolver(Assembler(bar, NeoHookean(4500.0, 0.49)))
    g1 = tip_load(bar, [0.0, 0.0, -80.0])
    first = solver.solve(g1)
    cold = solver.solve(1.05 * g1)
    warm = solver.solve(1.05 * g1, first.u)
    assert warm.converged and cold.converged
    assert warm.iterations < cold.iterations
    np.testing.assert_allclose(warm.u, cold.u, atol=1e-8)


def test_iteration_cap_is_reported_not_raised(bar):
    solver = NewtonSolver(Assembler(bar, NeoHookean(4500.0, 0.49)), NewtonOptions(max_iter=2))
    res = solver.solve(tip_load(bar, [0.0, 0.0, -150.0]))
    assert not res.converged
    assert res.status == "max_iter" and res.iterations == 2
    assert np.isfinite(res.u).all()


def test_a_solve_past_its_deadline_stops_before_its_next_iteration(bar):
    """A deadline already past: no Newton iteration is taken, nor the start's factorisation (a
    solve begun past its deadline factorised its tangent before reading the clock: a frame's
    overrun by one factorisation, the liver's ~1 s), the start comes back with status
    time_limit, and the same solver then converges to a fresh solver's answer (nothing left
    half-done)."""
    solver = NewtonSolver(Assembler(bar, NeoHookean(4500.0, 0.49)))
    g = tip_load(bar, [0.0, 0.0, -80.0])
    cut = solver.solve(g, deadline=time.perf_counter())
    assert not cut.converged and cut.status == "time_limit" and cut.iterations == 0
    assert solver.n_factor == 0
    assert not cut.u.any()
    full = solver.solve(g, deadline=time.perf_counter() + 3600.0)
    assert full.converged and full.iterations > 0
    np.testing.assert_allclose(full.u, NewtonSolver(Assembler(bar, NeoHookean(4500.0, 0.49))).solve(g).u, atol=1e-10)


def test_a_solve_begins_no_iteration_it_predicts_would_end_past_its_deadline(bar):
    """A deadline that leaves less than the longest of the solver's timed iterations: the solve
    stops before its first Newton iteration instead of passing the deadline by one; with ample
    time the same solver converges. The start holds the factor at u1, so the only work before
    the first iteration is its predictor (a back-substitution and a few force evaluations)."""
    solver = NewtonSolver(Assembler(bar, NeoHookean(4500.0, 0.49)))
    assert solver.iteration_estimate() == 0.0  # nothing timed yet: nothing predicted
    u1 = solver.solve(tip_load(bar, [0.0, 0.0, -60.0])).u
    g = tip_load(bar, [0.0, 0.0, -80.0])
    for _ in range(2):
        assert solver.factor_at(u1)
        estimate = solver.iteration_estimate()
        assert estimate == max(solver.iteration_seconds) > 0.0
        cut = solver.solve(g, u1, deadline=time.perf_counter() + 0.5 * estimate)
        assert cut.status == "time_limit" and cut.iterations == 0
    full = solver.solve(g, u1, deadline=time.perf_counter() + 60.0)
    assert full.converged and full.iterations > 0


def test_a_time_limit_result_measures_no_residual_past_its_deadline(bar):
    """Both time_limit paths (a deadline past before the start's factorisation; one nearer than
    an iteration, the factor held) carry no measure: reading the residual ran an internal-force
    pass past the deadline. An unconverged solve stopped for another reason still measures u's."""
    solver = NewtonSolver(Assembler(bar, NeoHookean(4500.0, 0.49)))
    g = tip_load(bar, [0.0, 0.0, -80.0])
    before = solver.solve(g, deadline=time.perf_counter())
    u1 = solver.solve(tip_load(bar, [0.0, 0.0, -60.0])).u
    assert solver.factor_at(u1)
    inside = solver.solve(g, u1, deadline=time.perf_counter() + 0.5 * solver.iteration_estimate())
    for cut in (before, inside):
        assert cut.status == "time_limit" and cut.measure is None and cut.residual is None
    capped = NewtonSolver(Assembler(bar, NeoHookean(4500.0, 0.49)), NewtonOptions(max_iter=2)).solve(g)
    assert capped.status == "max_iter" and capped.measure is not None and capped.residual > 1e-6


def test_one_stalled_iteration_does_not_refuse_every_later_solve(bar):
    """A single stall inside one iteration (a GC pause, the process descheduled: here 0.5 s of
    sleep before the real tangent) is the longest time the solver holds; a later budget under it
    is refused at most once, and the solves after it run again, re-timing their iterations."""
    asm = Assembler(bar, NeoHookean(4500.0, 0.49))
    solver = NewtonSolver(asm)
    solver.solve(tip_load(bar, [0.0, 0.0, -20.0]))
    tangent, stalled = asm.tangent, []

    def once_slow(u):
        if not stalled:
            stalled.append(time.sleep(0.5))
        return tangent(u)

    object.__setattr__(asm, "tangent", once_slow)
    solver.solve(tip_load(bar, [0.0, 0.0, -40.0]))
    object.__setattr__(asm, "tangent", tangent)
    assert stalled and solver.iteration_estimate() >= 0.5
    statuses = [solver.solve(tip_load(bar, [0.0, 0.0, -41.0 - k]), deadline=time.perf_counter() + 0.2).status
                for k in range(4)]  # fmt: skip
    assert statuses.count("time_limit") <= 1 and statuses[-1] == "converged", statuses
    assert solver.iteration_estimate() < 0.2


def test_non_finite_load_is_reported(bar):
    g = tip_load(bar, [0.0, 0.0, np.nan])
    res = NewtonSolver(Assembler(bar, NeoHookean(4500.0, 0.49))).solve(g)
    assert not res.converged and res.status == "non_finite"
    assert np.isfinite(res.u).all()


def test_tangent_solve_on_a_nearby_factor(bar):
    """Conjugate gradients preconditioned by the factor of a nearby tangent: the exact solve
    to the tolerance asked, or None where it cannot be (a far factor and a tight cap, an
    indefinite matrix), never a wrong answer."""
    import scipy.sparse.linalg as spla

    asm = Assembler(bar, NeoHookean(4500.0, 0.49))
    solver = NewtonSolver(asm)
    u1 = solver.solve(tip_load(bar, [0.0, 0.0, -40.0])).u
    u2 = solver.solve(tip_load(bar, [0.0, 0.0, -44.0]), u1).u
    assert solver.factor_at(u1)
    K2 = asm.tangent(u2)
    b = np.random.default_rng(0).normal(size=K2.shape[0])
    exact = spla.spsolve(K2.tocsc(), b)
    x = solver.solve_tangent(K2, b, 1e-10)
    np.testing.assert_allclose(x, exact, rtol=1e-8, atol=1e-10 * np.abs(exact).max())
    far = asm.tangent(solver.solve(tip_load(bar, [0.0, 0.0, -150.0])).u)
    assert solver.factor_at(u1)
    assert solver.solve_tangent(far, b, 1e-12, max_iter=2) is None
    assert solver.solve_tangent(-K2, b, 1e-6) is None  # negative curvature at once


def test_warm_solves_mostly_reuse_the_factor_and_agree_with_fresh_ones(bar):
    """A sequence of nearby loads from the last equilibrium (what a registration asks): fewer
    factorisations than Newton iterations, and the same equilibria as a fresh solver's."""
    asm = Assembler(bar, NeoHookean(4500.0, 0.49))
    solver = NewtonSolver(asm)
    u, iterations = None, 0
    for total in np.linspace(-20.0, -60.0, 6):
        g = tip_load(bar, [0.0, 5.0, total])
        res = solver.solve(g, u)
        assert res.converged
        fresh = NewtonSolver(asm).solve(g)
        np.testing.assert_allclose(res.u, fresh.u, atol=1e-7 * np.abs(fresh.u).max())
        u, iterations = res.u, iterations + res.iterations
        solver.factor_at(u)  # as a registration's adjoint does
    assert solver.n_cg > 0
    assert solver.n_factor < iterations


def test_a_start_with_no_finite_state_has_no_residual(bar):
    """A NaN start has no residual to report: null, not the 0.0 an empty history gave."""
    res = NewtonSolver(Assembler(bar, NeoHookean(4500.0, 0.49))).solve(
        tip_load(bar, [0.0, 0.0, -1.0]), u0=np.full((bar.n_nodes, 3), np.nan)
    )
    assert res.status == "non_finite" and res.residual is None

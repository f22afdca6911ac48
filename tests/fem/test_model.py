"""The FEM forward model: its adjoint against finite differences, torch autograd, stiffness."""

import time

import numpy as np
import pytest
import torch

from service.fem.material import NeoHookean
from service.fem.model import FEMModel
from service.fem.newton import NewtonOptions
from service.fem.response import FACTOR_IN_SOLVES
from service.forward import ForwardFailed, torch_forward
from tests.conftest import spare_threads_busy


@pytest.fixture(scope="module")
def model(bar):
    return FEMModel(bar, NeoHookean(4500.0, 0.49))


def support_and_load(mesh):
    support = mesh.free_surface_nodes[mesh.nodes[mesh.free_surface_nodes, 0] >= 3.0]
    rng = np.random.default_rng(0)
    g = rng.normal(size=(support.size, 3)) * 20.0 + [0.0, 0.0, -60.0]
    return support, g


def test_pullback_matches_finite_differences(model):
    support, g = support_and_load(model.mesh)
    nodes = model.mesh.surface_nodes[::3]
    op = model.restrict(support, nodes)
    u, pullback = op(g)
    assert np.abs(u).max() > 0.3  # the nonlinear regime
    u_bar = np.random.default_rng(1).normal(size=u.shape)
    grad = pullback(u_bar)
    # the reference: central differences of solves to 1e-12 (at the default 1e-9, a solve's
    # error over h is itself about 1e-6 of the derivative) with h = 2.5e-3 against loads of
    # ~50 (measured O(h^2) error: 2e-6 of the derivative at h = 1e-2, 2e-8 here)
    tight = FEMModel(model.mesh, model.material, NewtonOptions(rtol=1e-12)).restrict(support, nodes)
    h = 2.5e-3
    rng = np.random.default_rng(2)
    for _ in range(4):
        d = rng.normal(size=g.shape)
        fd = (np.sum(u_bar * tight(g + h * d)[0]) - np.sum(u_bar * tight(g - h * d)[0])) / (2 * h)
        assert np.sum(grad * d) == pytest.approx(fd, rel=1e-6)


def test_torch_autograd_uses_the_adjoint(model):
    support, g = support_and_load(model.mesh)
    op = model.restrict(support)
    gt = torch.tensor(g, requires_grad=True)
    u = torch_forward(op)(gt)
    (u**2).sum().backward()
    u_np, pullback = op(g)
    np.testing.assert_allclose(gt.grad.numpy(), pullback(2 * u_np), rtol=1e-6)  # two solves, to rtol 1e-9


def test_displacement_equals_solve(model):
    support, g = support_and_load(model.mesh)
    full = model.restrict(support).displacement(g)
    np.testing.assert_allclose(full, model.solve(g, support).u, atol=1e-10)


def test_displacement_at_a_recent_equilibrium_takes_no_newton_solve(model):
    """The field at forces the operator solved lately (a frame's best iterate, before its last
    evaluation) comes from the kept equilibrium: no Newton iteration, the same field as a fresh
    solve, a copy the caller may change; the next solve starts from it."""
    support, g = support_and_load(model.mesh)
    op = model.restrict(support)
    op(0.5 * g)
    op(g)
    last = op.last
    u = op.displacement(0.5 * g)
    assert op.last is last  # no solve ran
    np.testing.assert_allclose(u, model.solve(0.5 * g, support).u, atol=1e-8)
    u[:] = 0.0
    assert np.abs(op.displacement(0.5 * g)).max() > 0.0
    op(0.5 * g)
    assert op.last is last  # an evaluation there is the kept equilibrium too
    op.displacement(0.7 * g)  # never solved: a Newton solve
    assert op.last is not last and op.last.converged


def test_displacement_at_zero_load_is_the_rest_state_without_a_solve(model):
    """A frame whose best iterate is the rest state reads its field at zero load: exactly zero,
    with no Newton solve back from the latest equilibrium (that solve took a phantom frame's
    outputs 3-4 s past its time budget), and a copy the caller may change."""
    support, g = support_and_load(model.mesh)
    op = model.restrict(support)
    op(g)
    last, factors = op.last, op._newton.n_factor
    u = op.displacement(np.zeros_like(g))
    assert op.last is last and op._newton.n_factor == factors
    assert u.shape == (model.mesh.n_nodes, 3) and not np.any(u)
    u[:] = 1.0
    assert not np.any(op.displacement(np.zeros_like(g)))


def test_an_evaluation_at_the_last_forces_reuses_their_adjoints_factor(model):
    """A warm Newton frame starts where the last one ended: evaluating those forces again is
    the kept equilibrium, and its adjoint the factor the last evaluation left there (before, one
    more Newton iteration moved u by its tolerance and the adjoint factorised again)."""
    support, g = support_and_load(model.mesh)
    op = model.restrict(support)
    u_bar = np.ones((model.mesh.n_nodes, 3))
    u1, pullback = op(g)
    first = pullback(u_bar)
    factors = op._newton.n_factor
    u2, pullback = op(g)
    np.testing.assert_array_equal(u2, u1)
    np.testing.assert_array_equal(pullback(u_bar), first)
    assert op._newton.n_factor == factors


def test_jacobian_products_are_the_jacobians_own(model):
    """At a loaded g, du/dg x and du/dg^T y take a solve each with the factor the evaluation
    left there and equal the Jacobian formed in full at g; the latest full one (at an earlier
    g) comes along to precondition them. None where the full one is as cheap: before any was
    formed, at rest, at its own g."""
    support, g = support_and_load(model.mesh)
    op = model.restrict(support, model.mesh.surface_nodes[::3])
    op(g)
    assert op.jacobian_products(g) is None  # nothing held yet
    held = op.jacobian(0.5 * g)
    _, pullback = op(g)
    pullback(np.ones((op.nodes.size, 3)))  # the gradient at g, as the driver takes it first
    factors = op._newton.n_factor
    products = op.jacobian_products(g)
    assert products is not None and products.held is held
    assert op.jacobian_products(np.zeros_like(g)) is None and op.jacobian_products(0.5 * g) is None
    rng = np.random.default_rng(3)
    x, y = rng.normal(size=g.size), rng.normal(size=3 * op.nodes.size)
    Jx, Jty = products.matvec(x), products.rmatvec(y)
    assert products.n_solves == 2 and op._newton.n_factor == factors
    U = op.jacobian(g).U
    np.testing.assert_allclose(Jx, U @ x, rtol=1e-9, atol=1e-12 * np.abs(U @ x).max())
    np.testing.assert_allclose(Jty, U.T @ y, rtol=1e-9, atol=1e-12 * np.abs(U.T @ y).max())
    assert not np.allclose(held.U, U, rtol=1e-3)  # the held one is another g's
    products.deadline = time.perf_counter() - 1.0
    with pytest.raises(ForwardFailed, match="time_limit"):
        products.matvec(x)


@pytest.mark.parametrize("dense", [True, False])
def test_the_readout_at_other_nodes_is_the_rest_jacobians_there(model, monkeypatch, dense):
    """readout_at (the error estimate's whole surface): the rows of the estimate Jacobian at
    other nodes, in its own coefficients: the rest one's (3 solves a support node), or past
    MAX_JACOBIAN_SUPPORT the rest one's there times its leading directions' C^T."""
    import service.fem.model as fem_model

    support, _ = support_and_load(model.mesh)
    nodes, others = model.mesh.surface_nodes[:20], model.mesh.surface_nodes[20:27]
    if not dense:
        monkeypatch.setattr(fem_model, "MAX_JACOBIAN_SUPPORT", support.size - 1)
    op = model.restrict(support, nodes)
    there = model.restrict(support, others)._rest_dense().U
    jac = op.estimate_jacobian(np.zeros((support.size, 3)))
    want = there if dense else there @ jac.C.T
    np.testing.assert_allclose(op.readout_at(others), want, rtol=1e-9, atol=1e-12 * np.abs(there).max())


@pytest.mark.parametrize("estimate_first", [True, False])
def test_the_estimate_and_its_readout_share_one_set_of_rest_solves(model, monkeypatch, estimate_first):
    """A session with `matching` asks the rest Jacobian (estimate_jacobian) and its readout at
    the surface nodes the objective does not read (registration/outputs.py): 3k rest solve
    columns between them, in either order, not 3k each; the values are each one's own pass's."""
    support, _ = support_and_load(model.mesh)
    nodes = model.mesh.surface_nodes[:20]
    unread = np.setdiff1d(model.mesh.surface_nodes, nodes)  # as Outputs asks
    want_jac = model.restrict(support, nodes)._rest_dense().U
    want_readout = model.restrict(support, unread)._rest_dense().U
    op = model.restrict(support, nodes)
    rest = op._rest_solver()
    columns = []

    def counted(b):  # the real solver's solve, its right-hand sides counted
        columns.append(1 if b.ndim == 1 else b.shape[1])
        return solve_free(b)

    solve_free = rest.solve_free
    monkeypatch.setattr(rest, "solve_free", counted)
    zero = np.zeros((support.size, 3))
    if estimate_first:
        jac, readout = op.estimate_jacobian(zero), op.readout_at(unread)
    else:
        readout, jac = op.readout_at(unread), op.estimate_jacobian(zero)
    assert sum(columns) == 3 * support.size
    np.testing.assert_allclose(jac.U, want_jac, rtol=1e-12, atol=1e-15 * np.abs(want_jac).max())
    np.testing.assert_allclose(readout, want_readout, rtol=1e-12, atol=1e-15 * np.abs(want_readout).max())
    assert op._unread_rows is None  # handed over: the operator keeps only the objective's rows
    np.testing.assert_allclose(op.readout_at(unread), want_readout, rtol=1e-12, atol=1e-15 * np.abs(want_readout).max())


def test_with_stiffness_scales_the_response(model):
    support, g = support_and_load(model.mesh)
    stiff = model.with_stiffness(4 * model.material.E)
    np.testing.assert_allclose(stiff.solve(4 * g, support).u, model.solve(g, support).u, atol=1e-8)
    assert model.material.E == 4500.0  # the original is untouched


def test_with_stiffness_keeps_the_meshs_pattern_and_solves_as_a_fresh_model(model):
    """The API's per-request E makes a model of another stiffness: it keeps the mesh's sparsity
    pattern rather than remake it (0.3 s on the paper's liver) and solves as one built anew."""
    support, g = support_and_load(model.mesh)
    pattern = model.assembler._pattern
    stiff = model.with_stiffness(2 * model.material.E)
    assert stiff.assembler._pattern is pattern and stiff.assembler.material == stiff.material
    fresh = FEMModel(model.mesh, stiff.material)
    np.testing.assert_allclose(stiff.solve(g, support).u, fresh.solve(g, support).u, rtol=0, atol=1e-14)


def test_a_models_solve_past_its_deadline_makes_no_solver(bar):
    """A solve asked for past its deadline returns time_limit at its start (or rest) before it
    makes a solver: a fresh model's rest stiffness and pattern cost 0.2-0.3 s on the liver."""
    model = FEMModel(bar, NeoHookean(4500.0, 0.49))
    support, g = support_and_load(bar)
    res = model.solve(g, support, deadline=time.perf_counter())
    assert (res.status, res.converged, res.iterations) == ("time_limit", False, 0)
    assert "assembler" not in vars(model)
    np.testing.assert_array_equal(res.u, np.zeros((bar.n_nodes, 3)))
    u0 = np.full((bar.n_nodes, 3), 1e-4)
    start = model.solve(g, support, u0, deadline=time.perf_counter()).u  # the start as a solver takes it
    np.testing.assert_array_equal(start, np.where(np.isin(np.arange(bar.n_nodes), bar.fixed)[:, None], 0.0, u0))
    with pytest.raises(ValueError):  # a bad support is still refused first
        model.solve(g, np.array([bar.n_nodes]), deadline=time.perf_counter())
    assert model.solve(g, support, deadline=time.perf_counter() + 60).converged


def test_failed_solve_raises_forward_failed(bar):
    model = FEMModel(bar, NeoHookean(4500.0, 0.49), NewtonOptions(max_iter=1))
    support, g = support_and_load(bar)
    with pytest.raises(ForwardFailed) as info:
        model.restrict(support)(10 * g)
    assert info.value.status == "max_iter" and "after 1 iterations" in str(info.value)


def test_a_failed_trial_measures_no_residual_for_its_message(bar):
    """A trial point whose solve fails (a frame's line search may try many) paid an internal-force
    pass to put the field's residual in ForwardFailed's words: the residual is left unmeasured
    (residual is a cached property: its value lands in the result's __dict__ once read), and
    reading it after still gives simulate's measured residual."""
    model = FEMModel(bar, NeoHookean(4500.0, 0.49), NewtonOptions(max_iter=1))
    support, g = support_and_load(bar)
    op = model.restrict(support)
    with pytest.raises(ForwardFailed, match="no equilibrium after 1 iterations"):
        op(10 * g)
    assert "residual" not in vars(op.last)
    assert op.last.residual is not None and op.last.residual > 1e-6


def test_an_operator_past_its_deadline_fails_with_time_limit_and_keeps_its_state(model):
    """Past the deadline a solve raises ForwardFailed('time_limit') without a Newton iteration;
    the warm start it keeps is the last equilibrium, so the next solve without a deadline
    matches a fresh operator's."""
    support, g = support_and_load(model.mesh)
    op = model.restrict(support)
    u1, _ = op(0.5 * g)
    op.deadline = time.perf_counter()
    with pytest.raises(ForwardFailed, match="time budget") as info:
        op(g)
    assert info.value.status == "time_limit" and op.last.iterations == 0
    op.deadline = None
    u2, _ = op(g)
    np.testing.assert_allclose(u2, model.restrict(support)(g)[0], atol=1e-8)
    assert not np.allclose(u1, u2)


def test_an_operator_with_less_time_left_than_an_iteration_fails_before_it(model):
    """A deadline nearer than the operator's longest timed Newton iteration: the solve raises
    ForwardFailed('time_limit') without beginning one, rather than end one past the deadline."""
    support, g = support_and_load(model.mesh)
    op = model.restrict(support)
    op(0.5 * g)
    op.deadline = time.perf_counter() + 0.5 * op._newton.iteration_estimate()
    with pytest.raises(ForwardFailed, match="time budget") as info:
        op(g)
    assert info.value.status == "time_limit" and op.last.iterations == 0


def test_a_jacobian_past_its_deadline_stops_between_blocks_of_solves(model):
    """The Levenberg-Marquardt Jacobian (3 solves per support node, in blocks) gives up between
    blocks once the deadline has passed; the first block is always made."""
    support, g = support_and_load(model.mesh)
    op = model.restrict(support)
    solve = op._rest_solver().solve_free
    with pytest.raises(ForwardFailed, match="after 3 of") as info:
        op._support_response(solve, deadline=time.perf_counter(), block=3)
    assert info.value.status == "time_limit"
    full = op._support_response(solve, deadline=time.perf_counter() + 3600.0, block=3)
    np.testing.assert_allclose(full, op._support_response(solve), atol=1e-12)


def test_the_jacobian_solves_half_its_columns_on_a_spare_core(model):
    """Beside the caller, a second factor of the same tangent solves the last columns: the
    Jacobian equals the one made in turn. With every spare thread busy, the caller makes them
    all on its own factor, and no second factor is made."""
    support = model.mesh.free_surface_nodes
    assert 3 * support.size > 2 * FACTOR_IN_SOLVES  # a split pays
    g = np.random.default_rng(3).normal(size=(support.size, 3)) * 2.0
    nodes = model.mesh.surface_nodes
    op = model.restrict(support, nodes)
    op(g)
    u = op._last_u
    assert op._newton.factor_at(u)

    def patient(B):
        """The caller's solves, once the spare thread has begun its share (on this small bar
        the caller's half would otherwise end before a thread can start, and take it back)."""
        waited = time.monotonic() + 30.0
        while op._helper is None and time.monotonic() < waited:
            time.sleep(1e-3)
        return op._newton.solver.solve(B)

    split = op._support_response(patient, at=u)
    assert op._helper is not None
    in_turn = op._support_response(op._newton.solver.solve)
    np.testing.assert_allclose(split, in_turn, rtol=0, atol=1e-12 * np.abs(in_turn).max())
    busy = model.restrict(support, nodes)
    with spare_threads_busy():
        alone = busy.jacobian(g).U
    assert busy._helper is None
    np.testing.assert_allclose(alone, in_turn, rtol=0, atol=1e-12 * np.abs(in_turn).max())
    small = model.restrict(support[:5], nodes)  # 15 columns: fewer than a factorisation costs
    few = small.jacobian(g[:5]).U
    assert small._helper is None and few.shape == (3 * nodes.size, 15)
    np.testing.assert_allclose(few, small._support_response(small._newton.solver.solve), rtol=0, atol=1e-15)


def test_support_is_validated(model):
    with pytest.raises(ValueError, match="fixed"):
        model.restrict(model.mesh.fixed[:2])
    with pytest.raises(ValueError, match="integers"):
        model.restrict(np.array([1.5, 2.0]))
    with pytest.raises(ValueError, match="lie in"):
        model.restrict(np.array([10**6]))

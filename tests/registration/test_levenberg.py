"""Levenberg-Marquardt: its step solves the damped Gauss-Newton system, its rows are the
distance's derivatives, and it registers as well as L-BFGS-B in fewer evaluations, through the
network's Jacobian and through the FEM's."""

import dataclasses

import numpy as np
import pytest

import service.registration.drive_levenberg as driver
import service.registration.levenberg as lev
from service.forward import ForwardFailed
from service.registration.distance import PointToSurface
from service.registration.engine import SolveOptions, solve_frame
from service.registration.levenberg import GaussNewtonModel, KrylovGaussNewton, weighted_matrix, weighted_rows
from service.registration.session import Session, SessionConfig
from service.registration.stops import Stop

from .test_engine import frame_from_load, tip_pull, tip_support


def _explicit(jac, K):
    """C (r, K) from the product form, column by column."""
    return np.stack([jac.matvec(e) for e in np.eye(K)], axis=1)


@pytest.fixture(scope="module")
def loaded(entry):
    """The bar network at a loaded state, its cloud's match there, and the exact gradient."""
    mesh, support, g_true, _, dist = tip_pull(entry, entry.region)
    op = entry.network.restrict(support, dist.nodes)
    g = 0.5 * g_true
    u, pullback = op(g)
    J, dJ = dist(mesh.nodes[dist.nodes] + u)
    grad = pullback(dJ).ravel() + 1e-6 * g.ravel()
    return op, dist, g, grad


def test_step_solves_the_damped_gauss_newton_system(loaded):
    op, dist, g, grad = loaded
    jac = op.jacobian(g)
    model = GaussNewtonModel(jac, dist.last_match, dist.faces, grad, alpha=1e-6)
    C = _explicit(jac, g.size)
    H = C.T @ model.A @ C + 1e-6 * np.eye(g.size)
    for mu in (1e-3 * model.scale, model.scale):
        d = model.step(mu)
        np.testing.assert_allclose(
            (H + mu * np.eye(g.size)) @ d, -grad, rtol=1e-4, atol=1e-4 * np.abs(grad).max()
        )  # float32 C
        # the predicted decrease is the quadratic model's
        assert model.predicted(d, mu) == pytest.approx(-(grad @ d + 0.5 * d @ H @ d), rel=1e-4)
        assert model.predicted(d, mu) > 0


def test_rows_are_the_distance_derivatives(loaded):
    """sqrt(w_j) N_j c = the change of point j's distance along a change c of the coefficients
    (finite differences of the exact distance, closest points held: the envelope theorem),
    and the compiled rows equal NumPy's."""
    op, dist, g, _ = loaded
    jac = op.jacobian(g)
    match = dist.last_match
    N = weighted_rows(jac.U, match, dist.faces).astype(np.float64)
    compiled = lev._compiled
    try:
        lev._compiled = lambda: None
        N_np = weighted_rows(jac.U, match, dist.faces).astype(np.float64)
    finally:
        lev._compiled = compiled
    np.testing.assert_allclose(N, N_np, rtol=1e-5, atol=1e-6 * np.abs(N).max())
    c = np.random.default_rng(2).normal(size=jac.U.shape[1])
    dx = (jac.U.astype(np.float64) @ c).reshape(-1, 3)
    eps = 1e-6 / np.abs(dx).max()
    d0 = np.sqrt(dist.closest(match.x).sq_distances)
    d1 = np.sqrt(dist.closest(match.x + eps * dx).sq_distances)
    off = d0 > 1e-3 * d0.max()  # off the surface, where the distance is differentiable
    fd = (d1 - d0) / eps * np.sqrt(match.weight)
    np.testing.assert_allclose((N @ c)[off], fd[off], rtol=1e-2, atol=1e-3 * np.abs(fd).max())


@pytest.fixture(scope="module")
def fem_loaded(entry):
    """The bar's FEM at a loaded g with its gradient and match there, a Jacobian formed in
    full at an earlier g (held), the products at g, and then g's own Jacobian."""
    mesh, support, g_true, _, dist = tip_pull(entry)
    op = entry.fem.restrict(support, dist.nodes)
    op(0.6 * g_true)
    held = op.jacobian(0.6 * g_true)
    g = 0.8 * g_true
    u, pullback = op(g)
    _, dJ = dist(mesh.nodes[dist.nodes] + u)
    grad = pullback(dJ).ravel() + 1e-6 * g.ravel()
    products = op.jacobian_products(g)
    assert products is not None and products.held is held
    return op, dist, g, grad, products, op.jacobian(g)


def test_krylov_step_solves_the_damped_gauss_newton_system(fem_loaded):
    """Conjugate gradients through the exact Jacobian's products, preconditioned by the held
    one's model, reach the step to KRYLOV_RTOL in a few iterations; the predicted decrease is
    the quadratic model's at the step taken; preconditioned by g's own Jacobian, one iteration."""
    op, dist, g, grad, products, jac = fem_loaded
    match = dist.last_match
    model = KrylovGaussNewton(products, match, dist.faces, grad, alpha=1e-6)
    exact = GaussNewtonModel(jac, match, dist.faces, grad, alpha=1e-6)
    H = exact.A + 1e-6 * np.eye(g.size)  # C = I: the FEM's Jacobian is U itself
    N = weighted_matrix(match, dist.faces, jac.U.shape[0])
    np.testing.assert_allclose(jac.U.T @ (N.T @ (N @ jac.U)), exact.A, rtol=1e-9, atol=1e-12 * np.abs(exact.A).max())
    for mu in (1e-3 * exact.scale, exact.scale):
        d = model.step(mu)
        assert d is not None and 1 <= model.iterations <= 4, model.iterations
        residual = np.linalg.norm((H + mu * np.eye(g.size)) @ d + grad)
        assert residual <= lev.KRYLOV_RTOL * np.linalg.norm(grad) * (1 + 1e-6)
        assert model.predicted(d, mu) == pytest.approx(-(grad @ d + 0.5 * d @ H @ d), rel=1e-8)
        d_exact = exact.step(mu)
        assert np.linalg.norm(d - d_exact) <= 0.1 * np.linalg.norm(d_exact)
    with pytest.raises(ValueError, match="last step"):
        model.predicted(d.copy(), mu)
    held, products.held = products.held, jac
    try:
        own = KrylovGaussNewton(products, match, dist.faces, grad, alpha=1e-6)
        assert own.step(exact.scale) is not None and own.iterations == 1
    finally:
        products.held = held


def test_a_krylov_step_gives_up_on_a_held_jacobian_far_from_its_own(fem_loaded, monkeypatch):
    """A held Jacobian that no longer resembles g's preconditions badly: past KRYLOV_MAX_ITER
    the step gives None (the caller forms g's Jacobian), having spent two solves an iteration."""
    op, dist, g, grad, products, jac = fem_loaded
    held = products.held
    rng = np.random.default_rng(4)
    products.held = type(held)(rng.normal(size=held.U.shape) * np.abs(held.U).max())
    try:
        model = KrylovGaussNewton(products, dist.last_match, dist.faces, grad, alpha=1e-6)
        before = products.n_solves
        monkeypatch.setattr(lev, "KRYLOV_MAX_ITER", 3)
        assert model.step(model.scale) is None
        assert products.n_solves - before == 2 * 3
    finally:
        products.held = held


def test_a_krylov_step_past_the_deadline_is_the_frames_time_limit(fem_loaded):
    """The products' solves check the frame's deadline: past it the step stops the frame with
    status time_limit (as the Jacobian's blocks of solves do), keeping its iterations."""
    op, dist, g, grad, products, jac = fem_loaded
    deadline, products.deadline = products.deadline, 0.0  # long past
    try:
        model = KrylovGaussNewton(products, dist.last_match, dist.faces, grad, alpha=1e-6)
        with pytest.raises(Stop) as stop:
            driver._step(model, model.scale, 3)
        assert stop.value.status == "time_limit" and stop.value.iterations == 3
    finally:
        products.deadline = deadline


def test_fem_frames_step_through_products_once_a_jacobian_is_held(entry, monkeypatch):
    """A stream of FEM frames with Levenberg-Marquardt forms the Jacobian in full only where no
    held one preconditions well; the frames step through its products in a few solves and land
    where frames forming the Jacobian at every step land (those with KRYLOV_MAX_ITER 0)."""
    mesh = entry.mesh
    support = tip_support(mesh)
    config = SessionConfig(method="fem", optimizer="levenberg-marquardt", support=tuple(support), gtol=1e-5,
                           outputs=("forces",))  # fmt: skip
    clouds = []
    for k, scale in enumerate((1.0, 1.04, 1.08, 1.12)):
        g_true = np.tile([0.0, 0.0, -40.0 * scale / support.size], (support.size, 1))
        clouds.append(frame_from_load(mesh, support, g_true, seed=k)[1])

    def stream():
        s = Session(entry.fem, config)
        results = [s.frame(c) for c in clouds]
        assert all(r.converged for r in results), [r.status for r in results]
        return s.op, results

    op, fast = stream()
    monkeypatch.setattr(lev, "KRYLOV_MAX_ITER", 0)  # every step through a Jacobian formed in full
    op_full, full = stream()
    assert sum(r.iterations for r in fast[1:]) >= 2  # warm frames that stepped
    assert op.n_jacobians < op_full.n_jacobians and op.n_jacobians <= 2, (op.n_jacobians, op_full.n_jacobians)
    for a, b in zip(fast, full, strict=True):
        fa, fb = np.asarray(a.outputs["forces"]).sum(0), np.asarray(b.outputs["forces"]).sum(0)
        assert np.linalg.norm(fa - fb) <= 1e-3 * np.linalg.norm(fb)


def _register(entry, optimizer, pts, support, model, **kw):
    dist = PointToSurface(entry.mesh.surface_faces, **kw)
    dist.bind(pts)
    op = model.restrict(support, dist.nodes)
    options = SolveOptions(alpha=1e-6, gtol=1e-4, max_iter=300, optimizer=optimizer)
    return solve_frame(op, dist, entry.mesh.nodes[dist.nodes], np.zeros((support.size, 3)), options), op


@pytest.mark.parametrize("method, loss", [("network", "squared"), ("network", "trimmed"), ("fem", "squared")])
def test_registers_as_lbfgsb_does_in_fewer_evaluations(entry, method, loss):
    """A frame made by the FEM from a known load: Levenberg-Marquardt through the model's
    Jacobian (the network's, or the FEM's: fewer Newton solves) reaches the objective L-BFGS-B
    reaches, in fewer evaluations, and recovers the deformation as closely."""
    mesh = entry.mesh
    support = tip_support(mesh, entry.region)
    g_true = np.tile([0.0, 0.5, -40.0 / support.size], (support.size, 1))
    u_true, pts = frame_from_load(mesh, support, g_true)
    kw = {"loss": loss, "model": entry.fem if method == "fem" else entry.network}
    sol = {opt: _register(entry, opt, pts, support, **kw) for opt in ("lbfgsb", "levenberg-marquardt")}
    err = {}
    for opt, (s, op) in sol.items():
        assert s.status == "converged", (opt, s.status, s.message)
        err[opt] = np.linalg.norm(op.displacement(s.g) - u_true, axis=1).mean()
    lm, lb = sol["levenberg-marquardt"][0], sol["lbfgsb"][0]
    print(
        f"{method}, {loss}: L-BFGS-B {lb.evaluations} evaluations, TRE {err['lbfgsb']:.3e}; "
        f"LM {lm.evaluations}, {err['levenberg-marquardt']:.3e}"
    )
    assert lm.evaluations < lb.evaluations
    assert err["levenberg-marquardt"] <= 1.2 * err["lbfgsb"] + 1e-3 * np.linalg.norm(u_true, axis=1).mean()
    assert lm.value <= lb.value * (1 + 1e-3)


def damping_trace(entry, monkeypatch):
    """A tip pull's cloud to register with the network, and a record of each step's damping.

    Returns (g_true, run, seen): run(g0, options) clears seen and registers the cloud from g0;
    seen then holds (mu, the model's mean curvature) of every step taken.
    """
    mesh = entry.mesh
    support = tip_support(mesh, entry.region)
    g_true = np.tile([0.0, 0.5, -40.0 / support.size], (support.size, 1))
    _, pts = frame_from_load(mesh, support, g_true)
    seen = []
    step = GaussNewtonModel.step
    monkeypatch.setattr(GaussNewtonModel, "step", lambda self, mu: seen.append((mu, self.scale)) or step(self, mu))
    dist = PointToSurface(mesh.surface_faces)
    dist.bind(pts)
    op = entry.network.restrict(support, dist.nodes)

    def run(g0, options):
        seen.clear()
        return solve_frame(op, dist, mesh.nodes[dist.nodes], g0, options)

    return g_true, run, seen


def test_the_damping_never_falls_below_its_floor(entry, monkeypatch):
    """Each good step cuts the damping (by 3 at most), but never below _MIN_DAMPING times the
    frame's first model's mean curvature; a tolerance the float32 network cannot reach makes
    the frame take enough steps to reach the floor."""
    g_true, run, seen = damping_trace(entry, monkeypatch)
    run(np.zeros_like(g_true), SolveOptions(alpha=1e-6, gtol=1e-12, max_iter=40, optimizer="levenberg-marquardt"))
    mu = np.array([m for m, _ in seen])
    floor = driver._MIN_DAMPING * seen[0][1]
    assert len(seen) >= 10 and mu.min() >= floor * (1 - 1e-12)
    assert np.isclose(mu, floor, rtol=1e-9, atol=0.0).any()  # it got there


def test_from_rest_trusted_steps_cut_the_damping_faster(entry, monkeypatch):
    """From rest, a step the model predicted well (gain ratio above _TRUSTED_GAIN) cuts the
    damping by _COLD_SHRINK; from a warm start no step cuts it by more than Nielsen's 1/3."""
    g_true, run, seen = damping_trace(entry, monkeypatch)
    options = SolveOptions(alpha=1e-6, gtol=1e-6, max_iter=40, optimizer="levenberg-marquardt")
    ratios = {}
    for start, g0 in (("cold", np.zeros_like(g_true)), ("warm", 0.5 * g_true)):
        s = run(g0, options)
        assert s.iterations >= 3
        mu = np.array([m for m, _ in seen])
        ratios[start] = mu[1:] / mu[:-1]
    assert np.isclose(ratios["cold"], driver._COLD_SHRINK, rtol=1e-12).sum() >= 2
    assert ratios["warm"].min() >= 1.0 / 3.0 * (1 - 1e-12)


@pytest.mark.parametrize("at", ["rest", "loaded"])
def test_fem_jacobian_matches_finite_differences(entry, at):
    """The FEM's du/dg on the operator's nodes, at rest and at a loaded equilibrium, against
    central differences of Newton solves; asked again at the same g it is the same object."""
    mesh, support, g_true, _, dist = tip_pull(entry)
    op = entry.fem.restrict(support, dist.nodes)
    g = np.zeros_like(g_true) if at == "rest" else 0.8 * g_true
    if at == "loaded":
        op(g)  # as the driver does: the evaluation first, then the Jacobian at its equilibrium
    jac = op.jacobian(g)
    assert jac.U.shape == (3 * dist.nodes.size, 3 * support.size) and op.jacobian(g) is jac
    dg = np.random.default_rng(5).normal(size=g.shape) * 1e-3 * max(np.abs(g_true).max(), 1.0)
    fd = (op.displacement(g + dg)[dist.nodes] - op.displacement(g - dg)[dist.nodes]).ravel() / 2
    np.testing.assert_allclose(jac.U @ dg.ravel(), fd, rtol=1e-4, atol=1e-4 * np.abs(fd).max())


def test_limits_and_failures_are_statuses(entry):
    mesh, support, _, _, dist = tip_pull(entry, entry.region)
    op = entry.network.restrict(support, dist.nodes)
    rest, g0 = mesh.nodes[dist.nodes], np.zeros((support.size, 3))
    base = SolveOptions(alpha=1e-6, gtol=1e-9, optimizer="levenberg-marquardt")
    s = solve_frame(op, dist, rest, g0, dataclasses.replace(base, max_iter=1))
    assert s.status == "max_iter" and s.iterations == 1 and not s.converged
    s = solve_frame(op, dist, rest, g0, dataclasses.replace(base, time_budget=1e-9))
    assert s.status == "time_limit" and np.isfinite(s.g).all()
    # below the float32 network's precision no step decreases the objective: a status, soon
    s = solve_frame(op, dist, rest, g0, dataclasses.replace(base, gtol=1e-14, max_iter=200))
    assert s.status == "stalled" and s.evaluations < 150, (s.status, s.evaluations)

    def at_rest_only(f):
        """f, failing as a diverged Newton solve would anywhere but at rest."""

        def call(g):
            if np.any(g):
                raise ForwardFailed("diverged", "test")
            return f(g)

        return call

    class Failing:  # every trial away from rest fails: damping grows, then the frame gives up
        def __init__(self, op):
            self.op, self.support, self.nodes = op, op.support, op.nodes

        def __call__(self, g):
            return at_rest_only(self.op)(g)

        def jacobian(self, g):
            return self.op.jacobian(g)

    s = solve_frame(Failing(op), dist, rest, g0, base)
    assert s.status == "forward_failed" and not np.any(s.g)

    class FailingJacobian(Failing):  # the FEM's Jacobian solves again where g was not its last
        def __call__(self, g):
            return self.op(g)

        def jacobian(self, g):
            return at_rest_only(self.op.jacobian)(g)

    s = solve_frame(FailingJacobian(op), dist, rest, g0, base)  # the frame reports the step it took
    assert s.status == "forward_failed" and s.iterations == 1 and np.any(s.g) and np.isfinite(s.g).all()


@pytest.mark.parametrize("method", ["network", "fem"])
def test_a_session_readies_the_compiled_rows_when_it_opens(entry, method):
    """Opening a Levenberg-Marquardt session compiles the rows kernel for the types its
    frames use, so a frame compiles nothing (a first frame used to pay 0.3 s to seconds inside
    its time budget)."""
    K = lev._compiled()
    if K is None:
        pytest.skip("numba is not importable")
    kernel = K._rows_loop
    _, support, _, pts, _ = tip_pull(entry)
    model = entry.network if method == "network" else entry.fem
    session = Session(model, SessionConfig(method=method, optimizer="levenberg-marquardt", support=tuple(support)))
    compiled = set(kernel.signatures)
    assert {sig[0].dtype.name for sig in compiled} >= {"float32", "float64"}  # both Jacobians'
    assert session.frame(pts).iterations > 0
    assert set(kernel.signatures) == compiled


def test_session_checks_the_optimizer(entry):
    with pytest.raises(ValueError, match="optimizer must be one of"):
        Session(entry.network, SessionConfig(optimizer="newton"))
    with pytest.raises(ValueError, match="no force bounds"):
        Session(entry.network, SessionConfig(optimizer="levenberg-marquardt", force_bound=1.0))
    mesh, support, _, _, dist = tip_pull(entry)
    Session(entry.fem, SessionConfig(method="fem", optimizer="levenberg-marquardt", support=tuple(support)))

    class NoJacobian:  # an operator that offers no Jacobian (as the paper's network layout)
        def __init__(self, op):
            self.op, self.support, self.nodes = op, op.support, op.nodes

        def __call__(self, g):
            return self.op(g)

    op = NoJacobian(entry.network.restrict(support, dist.nodes))  # called directly, the engine refuses
    with pytest.raises(ValueError, match="needs a forward model with a Jacobian"):
        solve_frame(
            op, dist, mesh.nodes[dist.nodes], np.zeros((support.size, 3)), SolveOptions(optimizer="levenberg-marquardt")
        )
    with pytest.raises(ValueError, match="no force bounds"):  # nor bounds, called directly
        solve_frame(op.op, dist, mesh.nodes[dist.nodes], np.zeros((support.size, 3)),
                    SolveOptions(optimizer="levenberg-marquardt", force_bound=1.0))  # fmt: skip


def test_fem_refuses_a_support_too_large_for_its_jacobian(entry, monkeypatch):
    """Each step takes 3 solves a support node: past the limit a session says so when it opens."""
    import service.fem.model as fem_model

    support = tip_support(entry.mesh)
    monkeypatch.setattr(fem_model, "MAX_JACOBIAN_SUPPORT", support.size - 1)
    with pytest.raises(ValueError, match=f"at most {support.size - 1} support nodes"):
        Session(entry.fem, SessionConfig(method="fem", optimizer="levenberg-marquardt", support=tuple(support)))
    Session(entry.fem, SessionConfig(method="fem", support=tuple(support)))  # L-BFGS-B needs none


def test_a_stream_warm_starts_and_survives_a_bad_frame(entry):
    """Frames of a slowly growing pull: warm starts take fewer evaluations than the first
    frame; a cloud 20 m away (within the reach) returns a result and the next frame is as good as before."""
    mesh = entry.mesh
    support = tip_support(mesh, entry.region)
    s = Session(entry.network, SessionConfig(optimizer="levenberg-marquardt", support=tuple(support), gtol=1e-4,
                                             outputs=("displacement",)))  # fmt: skip
    frames = []
    for k, scale in enumerate((1.0, 1.05, 1.1)):
        g_true = np.tile([0.0, 0.0, -40.0 * scale / support.size], (support.size, 1))
        u, pts = frame_from_load(mesh, support, g_true, seed=k)
        frames.append((u, pts))
    first = s.frame(frames[0][1])
    second = s.frame(frames[1][1])
    assert first.converged and second.converged
    assert second.evaluations < first.evaluations
    far = s.frame(frames[1][1] + 20.0)
    assert np.isfinite(far.outputs["displacement"]).all()
    third = s.frame(frames[2][1])
    assert third.converged
    err = np.linalg.norm(third.outputs["displacement"] - frames[2][0], axis=1).mean()
    assert err <= 0.1 * np.linalg.norm(frames[2][0], axis=1).mean()

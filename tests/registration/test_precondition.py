"""Preconditioners: the low-rank Gauss-Newton factor is the exact factor of its matrix, and a
cold start preconditioned with it registers as well as one without."""

import numpy as np
import pytest

from service.registration.precondition import Curvature, LowRankPreconditioner
from service.registration.session import Session, SessionConfig
from service.synthetic import make_sequence


def test_low_rank_factor_is_exact():
    """For H = Q S Q^T + lam (I - Q Q^T): |L^-1 v|^2 = v^T H^-1 v, to_z inverts to_g, and
    grad_z is the adjoint of to_g (what L-BFGS-B's chain rule needs)."""
    rng = np.random.default_rng(0)
    K, r, lam = 40, 6, 0.05
    Q, _ = np.linalg.qr(rng.normal(size=(K, r)))
    A = rng.normal(size=(r, r))
    S = A @ A.T + 0.1 * np.eye(r)
    H = Q @ S @ Q.T + lam * (np.eye(K) - Q @ Q.T)
    P = LowRankPreconditioner(Q, S, lam)
    P.set_step(rng.normal(size=K))
    v, z = rng.normal(size=K), rng.normal(size=K)
    w = P.whiten(v)
    assert w @ w == pytest.approx(v @ np.linalg.solve(H, v), rel=1e-10)
    np.testing.assert_allclose(P.to_z(P.to_g(z)), z, rtol=1e-10, atol=1e-12)
    assert P.grad_z(v) @ z * P.value_scale == pytest.approx(v @ P.to_g(z), rel=1e-10)


def test_fem_low_rank_jacobian_is_the_small_load_response(entry):
    """U Q^T dg is the FEM's response to a small load dg (finite difference from rest)."""
    mesh = entry.mesh
    support = entry.region[::3]
    nodes = mesh.surface_nodes[::2]
    op = entry.fem.restrict(support, nodes)
    U, Q = op.low_rank_jacobian()
    np.testing.assert_allclose(Q.T @ Q, np.eye(Q.shape[1]), atol=1e-10)
    dg = np.random.default_rng(1).normal(size=(support.size, 3))
    eps = 1e-4
    fd = (op(eps * dg)[0] - op(-eps * dg)[0]).ravel() / (2 * eps)
    np.testing.assert_allclose(U @ (Q.T @ dg.ravel()), fd, rtol=1e-3, atol=1e-4 * np.abs(fd).max())


@pytest.mark.parametrize("method", ["network", "fem"])
def test_cold_start_with_gauss_newton_registers_as_well(entry, method):
    mesh = entry.mesh
    tip = entry.region[np.argsort(mesh.nodes[entry.region, 0])[-6:]]
    seq = make_sequence(mesh, entry.fem.material, tip, n_frames=6, peak_force=30.0, n_points=300, seed=4)
    model = entry.network if method == "network" else entry.fem
    # the float32 network's objective is precise to about 1e-7 of its value: a tolerance of
    # 1e-5 lies at that limit, where a stall (no relative decrease left) is luck's choice
    gtol = 1e-4 if method == "network" else 1e-5
    out = {}
    for pc in (False, True):
        s = Session(
            model, SessionConfig(method=method, warm_start=False, precondition=pc, gtol=gtol, outputs=("displacement",))
        )
        assert s.config.precondition is pc
        out[pc] = [s.frame(c) for c in seq.clouds[1::2]]
    for plain, gn, truth in zip(out[False], out[True], seq.positions[1::2], strict=True):
        err = [np.linalg.norm(mesh.nodes + r.outputs["displacement"] - truth, axis=1).mean() for r in (plain, gn)]
        print(f"{method}: plain {plain.iterations} it, {err[0]:.2e}; Gauss-Newton {gn.iterations} it, {err[1]:.2e}")
        assert gn.converged
        assert err[1] <= 1.5 * err[0] + 1e-3 * np.linalg.norm(truth - mesh.nodes, axis=1).mean()


def test_curvature_follows_a_change_of_alpha():
    """The regulariser's Hessian is alpha I: a carried model moves by exactly the change."""
    rng = np.random.default_rng(1)
    c = Curvature(6)
    gs = [rng.normal(size=6) for _ in range(5)]
    A = np.diag(np.arange(1.0, 7.0))
    c.update(gs, [A @ g for g in gs])
    before = c.B.copy()
    c.shift(0.25)
    np.testing.assert_allclose(c.B, before + 0.25 * np.eye(6))

"""The network forward model: the NumPy hot path is the torch network and its exact adjoint."""

import numpy as np
import pytest
import torch

import service.surrogate.physics as physics_module
from service.fem.assembly import Assembler
from service.fem.material import NeoHookean
from service.surrogate.basis import fixed_signs, linear_response, pod_basis
from service.surrogate.layers import BlockDiagonal
from service.surrogate.model import NetworkModel
from service.surrogate.network import Ensemble, PaperSurrogate, ReducedSurrogate

MAT = NeoHookean(4500.0, 0.45)


@pytest.fixture(autouse=True)
def exact_linear_block(monkeypatch):
    """The operator against torch: the physics layout's linear block exact at these supports
    (the truncation has its own test)."""
    monkeypatch.setattr(physics_module, "LINEAR_RANK", 10**6)


def randomised(net: torch.nn.Module, seed: int = 0) -> torch.nn.Module:
    """Random weights everywhere (the trained zero-initialised last layer would hide bugs)."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn(p.shape, generator=gen) * 0.3)
    return net.eval()


@pytest.fixture(scope="module", params=["reduced", "ensemble", "paper", "physics", "physics-ensemble"])
def model(request, bar):
    region = bar.free_surface_nodes[bar.nodes[bar.free_surface_nodes, 0] > 1.0]
    n_in = 3 * region.size
    if request.param.startswith("physics"):
        rng = np.random.default_rng(0)
        lin = linear_response(Assembler(bar, MAT), region)  # (3n, 3R): features of real responses
        features, _ = pod_basis((lin @ rng.normal(size=(3 * region.size, 40))).T, 10)
        basis, _ = pod_basis(rng.normal(size=(40, 3 * bar.n_nodes)), 12)
        net = ReducedSurrogate(
            10,
            torch.from_numpy(basis),
            [32, 16],
            torch.randn(12, 10),
            1e-3,
            torch.full((12,), 1e-3),
            members=3 if request.param.endswith("ensemble") else 1,
            feature_basis=torch.from_numpy(features),
        )
    elif request.param in ("reduced", "ensemble"):
        rng = np.random.default_rng(0)
        basis, _ = pod_basis(rng.normal(size=(40, 3 * bar.n_nodes)), 12)
        net = ReducedSurrogate(
            n_in,
            torch.from_numpy(basis),
            [32, 16],
            torch.randn(12, n_in),
            2.0,
            torch.full((12,), 0.5),
            members=3 if request.param == "ensemble" else 1,
        )
    else:
        net = PaperSurrogate(n_in, 3 * bar.n_nodes, depth=3, force_scale=2.0, u_scale=0.1)
    return NetworkModel(bar, MAT, region, randomised(net), E0=MAT.E)


def case(model):
    support = model.region[::2]
    nodes = model.mesh.surface_nodes[::3]
    g = np.random.default_rng(1).normal(size=(support.size, 3))
    return support, nodes, g


def torch_reference(model, support, g):
    gt = torch.tensor(g.ravel(), dtype=torch.float32, requires_grad=True)
    return gt, torch_reference_at(model, support, gt)


def torch_reference_at(model, support, gt):
    """The torch network's displacement (n, 3) for flat support forces gt (3k,)."""
    if model.physics:  # the linear response (at E0, of the scaled forces) plus the remainder
        L0 = torch.from_numpy(model.compliance().response(support)).float()
        lin = L0 @ (gt * model.stiffness_factor)
        return (lin + model.net((lin @ model.net.feature_basis)[None])[0]).reshape(-1, 3)
    x = torch.zeros(3 * model.region.size, dtype=torch.float32)
    cols = torch.from_numpy(model.region_columns(support))
    x = x.index_put((cols,), gt * model.stiffness_factor)
    return model.net(x[None])[0].reshape(-1, 3)


def central_difference(op, g, d, u_bar, h=1e-2):
    """<u_bar, J d> of a network operator at g by a central difference, and its float32 rounding
    bound. The step is halved from `h` until every PReLU unit keeps its slope at g +- h d: the
    operator is then affine on the step (each layer's input affine, no sign change between its
    ends), so the difference is the derivative but for rounding. A fixed step can straddle a
    kink, and where kinks lie moves with the CPU: MKL's AVX-512 and AVX2 kernels gave
    pod_basis' 4th feature opposite signs (fixed_signs now fixes them), and a kink 0.65 h from g
    on the Xeon."""

    def slopes(x):
        return [s for _, s in op._hidden(np.asarray(x, np.float32).ravel())[1]]

    at = slopes(g)
    while not all(np.array_equal(a, b) for s in (1, -1) for a, b in zip(at, slopes(g + s * h * d), strict=True)):
        h /= 2
        assert h > 1e-6, "g lies on a kink"
    fd = (np.sum(u_bar * op(g + h * d)[0]) - np.sum(u_bar * op(g - h * d)[0])) / (2 * h)
    # each side's float32 terms round at eps of their size: measured 0.08-0.23 of this bound
    return fd, 2 * np.finfo(np.float32).eps * np.sum(np.abs(u_bar * op(g)[0])) / h


def test_operator_matches_the_torch_network(model):
    support, nodes, g = case(model)
    u, _ = model.restrict(support, nodes)(g)
    _, ref = torch_reference(model, support, g)
    np.testing.assert_allclose(u, ref.detach().numpy()[nodes], rtol=1e-4, atol=1e-5 * np.abs(u).max())
    full = model.restrict(support, nodes).displacement(g)
    np.testing.assert_allclose(full, ref.detach().numpy(), rtol=1e-4, atol=1e-5 * np.abs(full).max())


def test_displacement_after_an_evaluation_is_the_same_to_the_bit(model):
    """A frame's full answer reuses its last evaluation's hidden layers when g is that point:
    the same numbers as computed afresh, and a fresh computation elsewhere."""
    support, nodes, g = case(model)
    fresh = model.restrict(support, nodes).displacement(g)
    op = model.restrict(support, nodes)
    op(g)
    calls = []
    hidden = op._hidden
    op._hidden = lambda x: calls.append(x) or hidden(x)
    reused = op.displacement(g)
    np.testing.assert_array_equal(reused, fresh)
    assert not calls  # reused
    elsewhere = op.displacement(0.5 * g)  # not the last evaluation: computed
    assert len(calls) == 1
    np.testing.assert_array_equal(elsewhere, model.restrict(support, nodes).displacement(0.5 * g))


def test_pullback_is_torch_backpropagation(model):
    support, nodes, g = case(model)
    _, pullback = model.restrict(support, nodes)(g)
    u_bar = np.random.default_rng(2).normal(size=(nodes.size, 3))
    gt, ref = torch_reference(model, support, g)
    (ref[torch.as_tensor(np.array(nodes))] * torch.from_numpy(u_bar).float()).sum().backward()
    np.testing.assert_allclose(pullback(u_bar), gt.grad.numpy().reshape(-1, 3), rtol=1e-4, atol=1e-5)


def test_pullback_is_torch_backpropagation_for_a_sparse_cotangent(model):
    """A distance's gradient touches only the closest triangles' nodes: the pullback reads out
    through those rows alone, and must still be backpropagation exactly."""
    support, nodes, g = case(model)
    _, pullback = model.restrict(support, nodes)(g)
    u_bar = np.zeros((nodes.size, 3))
    few = np.random.default_rng(5).choice(nodes.size, size=max(1, nodes.size // 10), replace=False)
    u_bar[few] = np.random.default_rng(6).normal(size=(few.size, 3))
    gt, ref = torch_reference(model, support, g)
    (ref[torch.as_tensor(np.array(nodes))] * torch.from_numpy(u_bar).float()).sum().backward()
    np.testing.assert_allclose(pullback(u_bar), gt.grad.numpy().reshape(-1, 3), rtol=1e-4, atol=1e-5)


def test_pullback_through_given_rows_is_the_full_pullback(model):
    """The rows hint (the distance's gradient nodes) changes the work, not the answer, and a
    second call with the same row set reuses its gathered readout."""
    support, nodes, g = case(model)
    op = model.restrict(support, nodes)
    _, pullback = op(g)
    rng = np.random.default_rng(7)
    rows = np.sort(rng.choice(nodes.size, size=max(1, nodes.size // 5), replace=False))
    u_bar = np.zeros((nodes.size, 3))
    u_bar[rows] = rng.normal(size=(rows.size, 3))
    full = pullback(u_bar)
    np.testing.assert_allclose(pullback(u_bar, rows=rows), full, rtol=1e-5, atol=1e-6 * np.abs(full).max())
    np.testing.assert_allclose(pullback(2 * u_bar, rows=rows), 2 * full, rtol=1e-5, atol=1e-6 * np.abs(full).max())
    if op._readout is not None:  # the reduced layout gathers; the paper's has no readout
        assert sum(key is rows for key, _ in op._row_cache) == 1


def test_pullback_matches_finite_differences(model):
    support, nodes, g = case(model)
    op = model.restrict(support, nodes)
    u_bar = np.random.default_rng(3).normal(size=(nodes.size, 3))
    grad = op(g)[1](u_bar)
    d = np.random.default_rng(4).normal(size=g.shape)
    fd, rounding = central_difference(op, g, d, u_bar)
    assert np.sum(grad * d) == pytest.approx(fd, rel=0, abs=rounding)


def test_stiffness_scales_the_input(model):
    support, nodes, g = case(model)
    stiff = model.with_stiffness(3 * MAT.E)
    np.testing.assert_allclose(
        stiff.restrict(support, nodes)(3 * g)[0], model.restrict(support, nodes)(g)[0], rtol=1e-4, atol=1e-6
    )
    assert model.material.E == MAT.E


def test_support_outside_the_region_is_refused(model):
    outside = np.setdiff1d(model.mesh.free_surface_nodes, model.region)[:2]
    with pytest.raises(ValueError, match="outside the network's load region"):
        model.restrict(outside)


def test_linear_response_solves_the_rest_stiffness(bar):
    asm = Assembler(bar, MAT)
    region = bar.free_surface_nodes[:5]
    G = linear_response(asm, region)
    g = np.zeros((bar.n_nodes, 3))
    g[region[2], 1] = 1.0
    u = asm.unpack(np.linalg.solve(asm.stiffness_at_rest().toarray(), asm.pack(g)))
    np.testing.assert_allclose(G[:, 3 * 2 + 1], u.ravel(), atol=1e-12 * np.abs(u).max() + 1e-15)


def test_pod_basis_is_orthonormal_and_captures_a_low_rank_set():
    rng = np.random.default_rng(5)
    U = rng.normal(size=(50, 4)) @ rng.normal(size=(4, 90))
    basis, s = pod_basis(U, 4)
    np.testing.assert_allclose(basis.T @ basis, np.eye(4), atol=1e-5)
    np.testing.assert_allclose(U @ basis @ basis.T, U, atol=1e-4 * np.abs(U).max())
    assert (np.diff(s) <= 1e-6).all()


def test_pod_basis_signs_follow_the_data_not_the_computation():
    """The same snapshots (reordered, another seed's random start, perturbed by 1e-9) give the
    same basis, signs included: each column's entry of largest magnitude positive. A sign that
    follows rounding made networks built from the same data differ between CPUs."""
    rng = np.random.default_rng(7)
    left, right = np.linalg.qr(rng.normal(size=(50, 4)))[0], np.linalg.qr(rng.normal(size=(90, 4)))[0]
    U = left @ np.diag([8.0, 4.0, 2.0, 1.0]) @ right.T  # (50, 90): well-separated modes
    basis, _ = pod_basis(U, 4)
    peaks = basis[np.argmax(np.abs(basis), axis=0), np.arange(4)]
    assert (peaks > 0).all()
    for other in (U[rng.permutation(len(U))], U + 1e-9 * rng.normal(size=U.shape)):
        for seed in (0, 1, 2, 3):
            np.testing.assert_allclose(pod_basis(other, 4, seed)[0], basis, atol=1e-5)


def test_fixed_signs_flips_a_column_back_and_breaks_ties_by_the_lowest_index():
    basis = np.linalg.qr(np.random.default_rng(3).normal(size=(30, 5)))[0]
    fixed = fixed_signs(basis)
    flipped = fixed.copy()
    flipped[:, 2] *= -1
    np.testing.assert_array_equal(fixed_signs(flipped), fixed)
    np.testing.assert_array_equal(fixed_signs(fixed), fixed)
    tie = np.array([[-0.5, 0.5], [0.5, 0.5], [0.0, -0.5], [0.5, -0.5]])
    np.testing.assert_array_equal(fixed_signs(tie), [[0.5, 0.5], [-0.5, 0.5], [0.0, -0.5], [-0.5, -0.5]])


def test_low_rank_jacobian_is_the_network_jacobian_at_rest(model):
    """U Q^T is torch's du/dg at g = 0 on the operator's nodes, Q orthonormal; the paper's
    layout (no basis) offers none."""
    support, nodes, _ = case(model)
    op = model.restrict(support, nodes)
    jac = op.low_rank_jacobian()
    if isinstance(model.net, PaperSurrogate):
        assert jac is None
        return
    U, Q = jac
    rank = 3 * support.size if model.physics else 12  # the (exact) linear block's own rank
    assert U.shape == (3 * nodes.size, rank) and Q.shape == (3 * support.size, rank)
    np.testing.assert_allclose(Q.T @ Q, np.eye(rank), atol=1e-5)
    g0 = torch.zeros(3 * support.size)
    ref = torch.autograd.functional.jacobian(
        lambda g: torch_reference_at(model, support, g)[torch.as_tensor(np.array(nodes))].reshape(-1), g0
    )
    np.testing.assert_allclose(U @ Q.T, ref.numpy(), rtol=1e-3, atol=1e-4 * float(ref.abs().max()))


def _torch_coefficient_jacobian(model, support, g):
    """dc/dg of the torch network at g (r, 3k), in the operator's coefficient units."""
    net = model.net
    cols = torch.from_numpy(model.region_columns(support))

    def coef(gt):
        x = torch.zeros(3 * model.region.size, dtype=torch.float32).index_put((cols,), gt * model.stiffness_factor)
        return net.coefficients(x[None])[0]

    return (
        torch.autograd.functional.jacobian(coef, torch.tensor(g.ravel(), dtype=torch.float32))
        .numpy()
        .astype(np.float64)
    )


def _random_reduced(bar, hidden, rng, seed, members=1):
    """A randomised reduced surrogate (12 modes) on the bar's far-end free surface."""
    region = bar.free_surface_nodes[bar.nodes[bar.free_surface_nodes, 0] > 1.0]
    basis, _ = pod_basis(rng.normal(size=(40, 3 * bar.n_nodes)), 12)
    n_in = 3 * region.size
    net = ReducedSurrogate(
        n_in, torch.from_numpy(basis), hidden, torch.randn(12, n_in), 2.0, torch.full((12,), 0.5), members=members
    )
    return NetworkModel(bar, MAT, region, randomised(net, seed=seed), E0=MAT.E)


@pytest.mark.parametrize("hidden,members", [([32, 16], 1), ([24], 1), ([32, 16], 3), ([24], 2)])
def test_coefficient_jacobian_is_torch_jacobian(bar, hidden, members):
    """C = dc/dg at loaded states (slopes flipped from rest) in product form: C C^T, C v and
    C^T w against torch's Jacobian, U C against torch's du/dg, for one and two hidden layers,
    one network or an ensemble."""
    rng = np.random.default_rng(0)
    model = _random_reduced(bar, hidden, rng, seed=3, members=members)
    support, nodes, g1 = case(model)
    op = model.restrict(support, nodes)
    rest_slope = op._hidden(np.zeros(g1.size, np.float32))[1][0][1]
    assert np.count_nonzero(op._hidden(np.asarray(g1, np.float32).ravel())[1][0][1] != rest_slope)
    for scale in (1.0, 0.1, 0.02):
        g = scale * g1
        C = _torch_coefficient_jacobian(model, support, g)
        jac = op.jacobian(g)
        np.testing.assert_allclose(jac.gram(), C @ C.T, rtol=1e-4, atol=1e-5 * np.abs(C @ C.T).max())
        v, w = rng.normal(size=g.size), rng.normal(size=12)
        np.testing.assert_allclose(jac.matvec(v), C @ v, rtol=1e-4, atol=1e-5 * np.abs(C @ v).max())
        np.testing.assert_allclose(jac.rmatvec(w), C.T @ w, rtol=1e-4, atol=1e-5 * np.abs(C.T @ w).max())
    gt = torch.tensor(g1.ravel(), dtype=torch.float32)
    ref = torch.autograd.functional.jacobian(
        lambda q: torch_reference_at(model, support, q)[torch.as_tensor(np.array(nodes))].reshape(-1), gt
    )
    C = _torch_coefficient_jacobian(model, support, g1)
    np.testing.assert_allclose(
        op.jacobian(g1).U.astype(np.float64) @ C, ref.numpy(), rtol=1e-3, atol=1e-4 * float(ref.abs().max())
    )


@pytest.mark.parametrize(
    "hidden,members", [([48, 40], 1), ([40], 1), ([24, 20, 16], 1), ([48, 40], 3), ([24, 20, 16], 2)]
)
def test_coefficient_jacobian_along_a_path_is_the_fresh_one(bar, hidden, members):
    """Levenberg-Marquardt asks one operator for the Jacobian at point after point: its R and
    C C^T are kept and corrected by the PReLU units that flipped since the last call, refreshed
    in full every so often. Along a path of small steps each must equal a fresh operator's
    full computation, the corrections must actually run (up to two hidden layers), and three
    hidden layers take the full computation; an ensemble's block-diagonal layers too."""
    rng = np.random.default_rng(1)
    model = _random_reduced(bar, hidden, rng, seed=5, members=members)
    support, nodes, g1 = case(model)
    op = model.restrict(support, nodes)
    corrected = 0
    for t in np.linspace(0.05, 1.5, 60):
        g = t * g1
        jac = op.jacobian(g)
        if op._anchored._anchor is not None:
            corrected += op._anchored._anchor.corrections > 0
        fresh = model.restrict(support, nodes).jacobian(g)
        G = fresh.gram()
        np.testing.assert_allclose(jac.gram(), G, rtol=1e-4, atol=1e-5 * np.abs(G).max())
        np.testing.assert_allclose(jac.R, fresh.R, rtol=1e-4, atol=1e-5 * np.abs(fresh.R).max())
        v = rng.normal(size=g.size)
        np.testing.assert_allclose(jac.matvec(v), fresh.matvec(v), rtol=1e-4, atol=1e-5 * np.abs(fresh.matvec(v)).max())
    if len(hidden) <= 2:
        assert corrected >= 10
    else:
        assert op._anchored._anchor is None


@pytest.mark.parametrize("hidden,members", [([32, 16], 1), ([24], 1), ([32, 16], 3)])
def test_gradient_image_is_the_jacobian_times_the_last_gradient(bar, hidden, members):
    """Levenberg-Marquardt's right-hand side C grad, from the Gram and the last evaluation's
    pullback (no product over the K inputs), equals C (pullback + alpha g) at rest and loaded,
    with a sparse cotangent read out through its rows; it is unknown (None) for a point that
    was not the last evaluated, and for one whose pullback has not run."""
    rng = np.random.default_rng(2)
    model = _random_reduced(bar, hidden, rng, seed=4, members=members)
    support, nodes, g1 = case(model)
    op = model.restrict(support, nodes)
    alpha = 0.3
    for g in (np.zeros_like(g1), g1, 0.5 * g1, np.zeros_like(g1)):  # rest twice: its cached forward
        u, pullback = op(g)
        assert op.jacobian(g).gradient_image(alpha) is None  # the pullback has not run yet
        u_bar = np.zeros_like(u)
        rows = np.arange(0, len(nodes), 3)
        u_bar[rows] = rng.normal(size=(rows.size, 3))
        grad = pullback(u_bar, rows=rows) + alpha * g
        jac = op.jacobian(g)
        ref = jac.matvec(grad.ravel())
        np.testing.assert_allclose(jac.gradient_image(alpha), ref, rtol=1e-4, atol=1e-5 * np.abs(ref).max())
    op(0.25 * g1)  # a newer evaluation: the image at g1 is no longer known
    assert op.jacobian(g1).gradient_image(alpha) is None
    op(np.zeros_like(g1))[1](u_bar, rows=rows)
    op(np.zeros_like(g1))  # the rest state again (its cached forward), its pullback not yet run
    assert op.jacobian(np.zeros_like(g1)).gradient_image(alpha) is None


@pytest.mark.parametrize("members", [1, 3])
def test_physics_coefficient_jacobian_is_torch_jacobian_along_a_path(bar, members):
    """The physics layout's coefficients are the network's and the linear block's, whose
    rows of the last layer are zero (its coefficients are the forces): along a path of loaded
    states, C C^T, C v and C^T w agree with the dense C that C v gives column by column, and
    U C with torch's du/dg, corrections and refreshes included."""
    rng = np.random.default_rng(3)
    region = bar.free_surface_nodes[bar.nodes[bar.free_surface_nodes, 0] > 1.0]
    lin = linear_response(Assembler(bar, MAT), region)
    features, _ = pod_basis((lin @ rng.normal(size=(3 * region.size, 40))).T, 10)
    basis, _ = pod_basis(rng.normal(size=(40, 3 * bar.n_nodes)), 12)
    net = ReducedSurrogate(10, torch.from_numpy(basis), [32, 16], torch.randn(12, 10), 1e-3, torch.full((12,), 1e-3),
                           members=members, feature_basis=torch.from_numpy(features))  # fmt: skip
    # weights whose path flips units: 4 corrections for one member and for three (seed 7 flipped
    # none for one member once pod_basis fixed its signs: flips depend on the features' signs)
    model = NetworkModel(bar, MAT, region, randomised(net, seed=0), E0=MAT.E)
    support, nodes, g1 = case(model)
    op = model.restrict(support, nodes)
    corrected = 0
    for t in np.linspace(0.05, 1.5, 40):
        g = t * g1  # small steps: a few units flip at each
        jac = op.jacobian(g)
        corrected += op._anchored._anchor.corrections > 0
        K = g.size
        C = np.stack([jac.matvec(e) for e in np.eye(K)], axis=1)  # (r, K)
        np.testing.assert_allclose(jac.gram(), C @ C.T, rtol=1e-4, atol=1e-5 * np.abs(C @ C.T).max())
        w = rng.normal(size=C.shape[0])
        np.testing.assert_allclose(jac.rmatvec(w), C.T @ w, rtol=1e-4, atol=1e-5 * np.abs(C.T @ w).max())
        gt = torch.tensor(g.ravel(), dtype=torch.float32)
        ref = torch.autograd.functional.jacobian(
            lambda q: torch_reference_at(model, support, q)[torch.as_tensor(np.array(nodes))].reshape(-1), gt
        ).numpy()
        np.testing.assert_allclose(jac.U.astype(np.float64) @ C, ref, rtol=1e-3, atol=1e-4 * np.abs(ref).max())
    assert corrected >= 3


def test_paper_layout_offers_no_coefficient_jacobian(bar):
    region = bar.free_surface_nodes[bar.nodes[bar.free_surface_nodes, 0] > 1.0]
    net = PaperSurrogate(3 * region.size, 3 * bar.n_nodes, depth=3)
    model = NetworkModel(bar, MAT, region, randomised(net), E0=MAT.E)
    support, nodes, g = case(model)
    assert model.restrict(support, nodes).jacobian(g) is None


def test_block_diagonal_is_its_dense_matrix():
    """Products from either side, the transpose, rows and a float64 copy all equal those of
    the dense block-diagonal matrix (3 blocks of 5 x 4)."""
    rng = np.random.default_rng(6)
    blocks = rng.normal(size=(3, 5, 4)).astype(np.float32)
    D = np.zeros((15, 12), np.float32)
    for i, b in enumerate(blocks):
        D[5 * i : 5 * i + 5, 4 * i : 4 * i + 4] = b
    B = BlockDiagonal(blocks)
    x, X, A = rng.normal(size=12), rng.normal(size=(12, 2)), rng.normal(size=(7, 15))
    np.testing.assert_allclose(B @ x.astype(np.float32), D @ x, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(B @ X.astype(np.float32), D @ X, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(A.astype(np.float32) @ B, A @ D, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(B.T @ A[0].astype(np.float32), D.T @ A[0], rtol=1e-5, atol=1e-5)
    # the transpose is a view of the same weights (the pullback reads what the forward read)
    assert np.shares_memory(B.T.blocks, B.blocks) and B.T.T is B
    np.testing.assert_allclose(B.T @ A[:2].T.astype(np.float32), D.T @ A[:2].T, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(X.T.astype(np.float32) @ B.T, X.T @ D.T, rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(B.T[np.array([0, 11, 5])], D.T[[0, 11, 5]])
    rows = np.array([0, 7, 14, 6])
    np.testing.assert_array_equal(B[rows], D[rows])
    assert B.shape == D.shape and B.astype(np.float64).dtype == np.float64
    assert B.astype(np.float32, copy=False) is B


def test_an_ensemble_answers_the_mean_of_its_members(bar):
    """The network is its members' mean, and fresh members start apart (each its own
    initialisation: their hidden layers; the last layers start at zero)."""
    fresh = ReducedSurrogate(6, torch.eye(6, 2, dtype=torch.float64), [4], members=2).net.members
    assert (fresh[0][0].weight - fresh[1][0].weight).abs().max() > 1e-3
    rng = np.random.default_rng(3)
    model = _random_reduced(bar, [16, 8], rng, seed=2, members=3)
    net = model.net
    assert isinstance(net.net, Ensemble) and net.members == 3
    x = torch.randn(4, net.skip.in_features)
    each = net.member_coefficients(x)
    assert each.shape == (3, 4, 12)
    assert (each[0] - each[1]).abs().max() > 1e-3
    torch.testing.assert_close(net.coefficients(x), each.mean(0))
    with pytest.raises(ValueError, match="at least 1"):
        ReducedSurrogate(6, torch.eye(6, 2, dtype=torch.float64), [4], members=0)


@pytest.mark.parametrize("members", [1, 3])
def test_zero_at_rest_moves_each_member_by_a_constant_to_zero(bar, members):
    rng = np.random.default_rng(4)
    net = _random_reduced(bar, [16, 8], rng, seed=5, members=members).net
    x = torch.randn(5, net.skip.in_features)
    rest = torch.zeros(1, net.skip.in_features)
    before, at_rest = net.member_coefficients(x), net.member_coefficients(rest)
    assert at_rest.abs().max() > 1e-3  # random biases: not zero at rest to begin with
    net.zero_at_rest_()
    torch.testing.assert_close(net.member_coefficients(rest), torch.zeros_like(at_rest), atol=1e-6, rtol=0)
    torch.testing.assert_close(net.member_coefficients(x), before - at_rest)


def inmap(model: NetworkModel, support: np.ndarray) -> np.ndarray:
    """The physics layout's map from the support's forces to the network's input (x_scale 1)."""
    F = model.net.feature_basis.double().numpy()
    return physics_module.physics_input(model.compliance(), F, model.stiffness_factor, support, 1.0)[0]


@pytest.mark.parametrize("route", ["svd", "range finder"])
def test_a_large_support_keeps_the_leading_linear_directions(bar, monkeypatch, route):
    """Past LINEAR_RANK support dofs the physics layout's linear block is its leading singular
    directions: off the exact operator by at most the first dropped singular value per unit
    force (a few per cent more by the range finder a large support takes), and its pullback
    still its own forward's adjoint."""
    rng = np.random.default_rng(8)
    region = bar.free_surface_nodes
    lin = linear_response(Assembler(bar, MAT), region)
    features, _ = pod_basis((lin @ rng.normal(size=(3 * region.size, 30))).T, 8)
    basis, _ = pod_basis(rng.normal(size=(30, 3 * bar.n_nodes)), 6)
    net = ReducedSurrogate(
        8, torch.from_numpy(basis), [16], torch.randn(6, 8), 1e-3, torch.full((6,), 1e-3),
        feature_basis=torch.from_numpy(features),
    )  # fmt: skip
    model = NetworkModel(bar, MAT, region, randomised(net, seed=2), E0=MAT.E)
    support, g = region[:30], rng.normal(size=(30, 3))
    exact = model.restrict(support).displacement(g)
    monkeypatch.setattr(physics_module, "LINEAR_RANK", 12)
    svd_route = model.restrict(support).displacement(g)  # 90 dofs: fewer than the range finder's solves
    svd_inmap = inmap(model, support)
    if route == "range finder":  # 8 features + 4 (12 + 4) solves < 90
        monkeypatch.setattr(physics_module, "OVERSAMPLE", 4)
        monkeypatch.setattr(physics_module, "POWER", 1)
    np.testing.assert_allclose(inmap(model, support), svd_inmap, rtol=1e-5)
    op = model.restrict(support)
    assert op._readout.shape[1] == 6 + 12
    assert (route == "svd") == np.array_equal(op.displacement(g), svd_route)
    sv = np.linalg.svd(model.compliance().response(support), compute_uv=False)
    gap = np.linalg.norm(op.displacement(g) - exact)
    assert 0 < gap <= (1.01 if route == "svd" else 1.1) * sv[12] * np.linalg.norm(g)
    u_bar = rng.normal(size=(bar.n_nodes, 3))
    d = rng.normal(size=g.shape)
    fd, rounding = central_difference(op, g, d, u_bar)
    assert np.sum(op(g)[1](u_bar) * d) == pytest.approx(fd, rel=0, abs=rounding)


def test_the_rest_state_on_the_side_is_the_rest_state_and_records_nothing(bar):
    """at_rest() answers what a call at zero does, to the bit, and leaves the operator's own
    record alone: the last evaluation's gradient image is still known after its pullback runs
    (the engine runs it on another thread while a frame evaluates its start)."""
    rng = np.random.default_rng(5)
    model = _random_reduced(bar, [32, 16], rng, seed=6, members=1)
    support, nodes, g = case(model)
    op = model.restrict(support, nodes)
    u_bar = rng.normal(size=(len(nodes), 3))
    u, pullback = op(g)
    grad = pullback(u_bar)
    u0, pullback0 = op.at_rest()
    ref_u, ref_pullback = model.restrict(support, nodes)(np.zeros_like(g))
    np.testing.assert_array_equal(u0, ref_u)
    np.testing.assert_array_equal(pullback0(u_bar), ref_pullback(u_bar))
    jac = op.jacobian(g)
    ref = jac.matvec(grad.ravel())
    np.testing.assert_allclose(jac.gradient_image(0.0), ref, rtol=1e-4, atol=1e-5 * np.abs(ref).max())


def test_the_readout_at_other_nodes_is_their_operators_own(model):
    """readout_at (the error estimate's whole surface): the rows another operator, restricted
    to those nodes, reads through the same coefficients; None without a basis."""
    support, nodes, _ = case(model)
    others = np.setdiff1d(model.mesh.surface_nodes, nodes)[:7]
    got = model.restrict(support, nodes).readout_at(others)
    want = model.restrict(support, others).readout
    if want is None:
        assert got is None
    else:
        np.testing.assert_array_equal(got, want)

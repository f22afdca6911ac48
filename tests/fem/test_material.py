"""The pointwise Neo-Hookean law: derivatives, invariances, and its small-strain limit."""

import numpy as np
import pytest

from service.fem.material import NeoHookean, det3, inv_transpose

MAT = NeoHookean(E=4500.0, nu=0.45)


def random_F(n: int, scale: float = 0.3, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    F = np.eye(3) + scale * rng.normal(size=(n, 3, 3))
    flip = np.linalg.det(F) < 0
    F[flip] = F[flip][:, :, [1, 0, 2]]  # swap two columns: det > 0
    return F


def test_rest_state_is_stress_free():
    eye = np.eye(3)[None]
    assert MAT.energy(eye)[0] == 0.0
    np.testing.assert_allclose(MAT.stress(eye)[0], 0.0, atol=1e-12)


def test_stress_is_energy_gradient():
    F = random_F(20)
    h = 1e-6
    fd = np.zeros_like(F)
    for i in range(3):
        for j in range(3):
            dF = np.zeros((3, 3))
            dF[i, j] = h
            fd[:, i, j] = (MAT.energy(F + dF) - MAT.energy(F - dF)) / (2 * h)
    np.testing.assert_allclose(MAT.stress(F), fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())


def test_tangent_is_stress_gradient():
    F = random_F(20, seed=1)
    h = 1e-6
    A = MAT.tangent(F)
    for k in range(3):
        for L in range(3):
            dF = np.zeros((3, 3))
            dF[k, L] = h
            fd = (MAT.stress(F + dF) - MAT.stress(F - dF)) / (2 * h)
            np.testing.assert_allclose(A[:, :, :, k, L], fd, rtol=1e-5, atol=1e-5 * np.abs(A).max())


def test_tangent_has_major_symmetry():
    A = MAT.tangent(random_F(10, seed=2))
    np.testing.assert_allclose(A, A.transpose(0, 3, 4, 1, 2), atol=1e-9 * np.abs(A).max())


def test_small_strain_limit_is_linear_elasticity():
    A = MAT.tangent(np.eye(3)[None])[0]
    d = np.eye(3)
    C = MAT.lam * np.einsum("ij,kl->ijkl", d, d) + MAT.mu * (
        np.einsum("ik,jl->ijkl", d, d) + np.einsum("il,jk->ijkl", d, d)
    )
    np.testing.assert_allclose(A, C, atol=1e-9 * MAT.E)


def test_energy_is_frame_indifferent():
    F = random_F(10, seed=3)
    rng = np.random.default_rng(4)
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    Q *= np.sign(np.linalg.det(Q))
    np.testing.assert_allclose(MAT.energy(Q @ F), MAT.energy(F), rtol=1e-12)


def test_inverted_elements_have_infinite_energy():
    F = np.diag([1.0, 1.0, -0.5])[None]
    assert np.isinf(MAT.energy(F)[0])


def test_helpers_match_numpy():
    F = random_F(10, seed=5)
    np.testing.assert_allclose(det3(F), np.linalg.det(F), rtol=1e-12)
    np.testing.assert_allclose(inv_transpose(F, det3(F)), np.linalg.inv(F).transpose(0, 2, 1), rtol=1e-10)


@pytest.mark.parametrize("E,nu", [(0.0, 0.3), (-1.0, 0.3), (1.0, 0.5), (1.0, -0.1), (np.nan, 0.3)])
def test_bad_constants_are_refused(E, nu):
    with pytest.raises(ValueError):
        NeoHookean(E, nu)


def test_lame_constants():
    m = NeoHookean(4500.0, 0.49)
    assert m.mu == pytest.approx(4500 / 2.98)
    assert m.lam == pytest.approx(4500 * 0.49 / (1.49 * 0.02))


def test_the_law_of_a_scene_or_a_manifest():
    from service.scene import MaterialSpec

    spec = MaterialSpec(E=4500.0, nu=0.49)
    assert NeoHookean.of(spec) == NeoHookean(4500.0, 0.49)
    assert NeoHookean.of({"law": "neo-hookean", "E": 4500, "nu": 0.49}) == NeoHookean(4500.0, 0.49)
    with pytest.raises(KeyError):
        NeoHookean.of({"E": 4500.0})
    with pytest.raises(ValueError, match="Poisson"):
        NeoHookean.of({"E": 4500.0, "nu": 0.5})


@pytest.mark.parametrize(
    "E, nu, says",
    [
        (1e-3, 0.45, "E must be within [1, 1e+12] Pa, got 0.001"),
        (2e12, 0.45, "E must be within [1, 1e+12] Pa, got 2000000000000.0"),
        (float("nan"), 0.45, "E must be within"),
        (4500.0, 0.4999999, "nu must be within [0, 0.49999], got 0.4999999"),
        (4500.0, -0.1, "nu must be within [0, 0.49999], got -0.1"),
    ],
)
def test_the_law_refuses_constants_outside_the_range_a_scene_takes(E, nu, says):
    """Before: any positive E and nu < 0.5 made a law, though a scene refuses them."""
    with pytest.raises(ValueError) as err:
        NeoHookean(E, nu)
    assert says in str(err.value)
    with pytest.raises(ValueError):
        NeoHookean.of({"E": 4500.0, "nu": 0.45}).with_stiffness(E if nu == 0.45 else 0.5)


def test_the_ends_of_the_range_make_a_law():
    for E, nu in ((1.0, 0.0), (1e12, 0.49999)):
        assert NeoHookean(E, nu).mu > 0

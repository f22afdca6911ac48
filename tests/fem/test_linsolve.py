"""Every available sparse backend solves SPD systems and flags indefinite ones."""

import numpy as np
import pytest

from service.fem.assembly import Assembler
from service.fem.linsolve import NotPositiveDefinite, available_backends, make_solver
from service.fem.material import NeoHookean


@pytest.mark.parametrize("backend", available_backends())
def test_backend_solves_and_refactors(bar, backend):
    asm = Assembler(bar, NeoHookean(4500.0, 0.45))
    K = asm.stiffness_at_rest()
    solver = make_solver(K, backend)
    b = np.random.default_rng(0).normal(size=K.shape[0])
    for scale in (1.0, 3.0):  # a numeric refactorisation on the same pattern
        solver.factor(K * scale)
        x = solver.solve(b)
        assert np.linalg.norm(scale * (K @ x) - b) < 1e-10 * np.linalg.norm(b)
    B = np.stack([b, 2 * b], axis=1)
    np.testing.assert_allclose(solver.solve(B)[:, 1], 2 * solver.solve(b), rtol=1e-10)


@pytest.mark.parametrize("backend", available_backends())
def test_backend_flags_indefinite_matrix(bar, backend):
    K = Assembler(bar, NeoHookean(4500.0, 0.45)).stiffness_at_rest()
    solver = make_solver(K, backend)
    with pytest.raises(NotPositiveDefinite):
        solver.factor(-K)


def test_unknown_backend():
    with pytest.raises(ValueError, match="unknown solver backend"):
        make_solver(None, "magic")


@pytest.mark.parametrize("backend", available_backends())
def test_single_precision_solves_to_float32_accuracy(bar, backend):
    """The error estimate's factor: float32 where the backend has it, answers in float64."""
    K = Assembler(bar, NeoHookean(4500.0, 0.45)).stiffness_at_rest()
    solver = make_solver(K, backend, single=True)
    solver.factor(K)
    b = np.random.default_rng(1).normal(size=(K.shape[0], 2))
    x = solver.solve(b)
    exact = make_solver(K, backend)
    exact.factor(K)
    assert x.dtype == np.float64
    err = np.linalg.norm(x - exact.solve(b)) / np.linalg.norm(x)
    assert err < 1e-3  # a few digits, which is all an estimate needs
    if backend != "cholmod":  # CHOLMOD has no single precision: the same answer
        assert err > 1e-12

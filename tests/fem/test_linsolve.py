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


@pytest.mark.skipif("pardiso" not in available_backends(), reason="needs MKL PARDISO")
def test_a_frames_factorisation_takes_the_spare_core_and_solves_alike(bar):
    """A Newton method's solver factorises on PARDISO's two-thread instance inside a frame with a
    core to spare, on its one-thread instance elsewhere (a trainer's workers, a loaded server),
    and solves on whichever holds the latest factor: the same answers to rounding."""
    import os
    from contextlib import ExitStack

    from service import spare
    from service.fem.linsolve import FACTOR_THREADS, SpareCoreSolver

    K = Assembler(bar, NeoHookean(4500.0, 0.45)).stiffness_at_rest()
    b = np.random.default_rng(2).normal(size=K.shape[0])
    solver = make_solver(K, "pardiso", spare_core=True)
    assert isinstance(solver, SpareCoreSolver)
    solver.factor(K)  # no frame: one thread, the other instance not even analysed
    alone = solver.solve(b)
    assert solver._current is solver._one and solver._more is None
    with spare.frame():
        if (os.cpu_count() or 1) > 1:  # a core to spare
            solver.factor(2 * K)
            assert solver._current is solver._more and solver._more.threads == FACTOR_THREADS
            np.testing.assert_allclose(2 * solver.solve(b), alone, rtol=1e-10)
        with ExitStack() as others:  # every core now has a frame: none is spare
            for _ in range((os.cpu_count() or 1) - 1):
                others.enter_context(spare.frame())
            solver.factor(3 * K)
            assert solver._current is solver._one
            np.testing.assert_allclose(3 * solver.solve(b), alone, rtol=1e-10)
        with pytest.raises(NotPositiveDefinite):
            solver.factor(-K)
        with pytest.raises(RuntimeError, match="before a successful factor"):
            solver.solve(b)  # a failed factor refuses solves, as a lone solver does

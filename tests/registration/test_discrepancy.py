"""The discrepancy tracker: which way alpha moves, how far, and where it stops."""

import math

import pytest

from service.registration.discrepancy import TAU, AlphaTracker


def test_a_fit_below_the_noise_raises_alpha_by_a_bounded_step():
    t = AlphaTracker(1e-7, noise=1e-3)
    target = 0.5 * TAU * 1e-6
    assert t.target == pytest.approx(target)
    assert t.update(0.98 * target, converged=True) == pytest.approx(1e-7 * math.exp(-5 * math.log(0.98)))
    assert t.update(0.1 * target, converged=True) == pytest.approx(t.alpha)  # capped at x4
    assert t.alpha == pytest.approx(1e-7 * 0.98 ** -5 * 4)


def test_a_fit_above_the_noise_lowers_alpha_but_never_below_the_floor():
    t = AlphaTracker(1e-7, noise=1e-3)
    for _ in range(3):
        t.update(0.1 * t.target, converged=True)
    high = t.alpha
    assert t.update(1.05 * t.target, converged=True) < high
    for _ in range(20):
        t.update(10 * t.target, converged=True)
    assert t.alpha == 1e-7


def test_alpha_stays_under_its_ceiling():
    t = AlphaTracker(1e-7, noise=1e-3, ceiling=50.0)
    for _ in range(20):
        t.update(1e-3 * t.target, converged=True)
    assert t.alpha == pytest.approx(5e-6)


def test_an_unconverged_frame_may_raise_alpha_but_not_lower_it():
    t = AlphaTracker(1e-7, noise=1e-3)
    t.update(0.5 * t.target, converged=True)
    a = t.alpha
    assert t.update(3 * t.target, converged=False) == a
    assert t.update(0.5 * t.target, converged=False) > a


def test_a_meaningless_objective_leaves_alpha():
    t = AlphaTracker(1e-7, noise=1e-3)
    t.update(0.5 * t.target, converged=True)
    a = t.alpha
    for J in (float("nan"), float("inf"), 0.0, -1.0):
        assert t.update(J, converged=True) == a


@pytest.mark.parametrize("floor, noise", [(1e-7, 0.0), (1e-7, -1e-3), (1e-7, float("nan")), (0.0, 1e-3)])
def test_bad_settings_are_refused(floor, noise):
    with pytest.raises(ValueError):
        AlphaTracker(floor, noise)

"""The noise prior's alpha: the MAP weight (MacKay's), its damping, and the clamp that stops its collapse."""

import math

import numpy as np
import pytest

from service.registration.noise_prior import AlphaTracker


def test_alpha_moves_halfway_in_log_towards_the_map_weight():
    t = AlphaTracker(1e-7, noise=1e-3)
    g = np.full((10, 3), 0.02)  # mean g^2 = 4e-4
    rule = 1e-6 / (500 * 4e-4)  # sigma^2 / (m s^2) = 5e-6
    assert t.rule(g, 500) == pytest.approx(rule)
    assert t.update(g, 500) == pytest.approx(math.sqrt(1e-7 * rule))
    for _ in range(30):
        t.update(g, 500)
    assert t.alpha == pytest.approx(rule)


def test_the_rule_counts_the_directions_the_cloud_determines():
    """MacKay's update: |g|^2 over gamma, not over all K components (gamma None: all of them);
    a gamma that says nothing (zero, not finite) leaves alpha."""
    t = AlphaTracker(1e-9, noise=1e-3, ceiling=1e6)
    g = np.full((10, 3), 0.02)  # |g|^2 = 1.2e-2, K = 30
    assert t.rule(g, 500, gamma=6.0) == pytest.approx(1e-6 * 6.0 / (500 * 1.2e-2))
    assert t.rule(g, 500) == pytest.approx(t.rule(g, 500, gamma=30.0))
    assert t.rule(g, 500, gamma=6.0) == pytest.approx(t.rule(g, 500) / 5.0)
    a = t.alpha
    for gamma in (0.0, float("nan"), float("inf")):
        assert t.update(g, 500, gamma) == a


def test_alpha_stays_within_floor_and_ceiling():
    t = AlphaTracker(1e-7, noise=1e-3, ceiling=50.0)
    for _ in range(40):
        t.update(np.full((4, 3), 1e-9), 500)  # tiny forces: the bare rule would collapse
    assert t.alpha == pytest.approx(5e-6)
    for _ in range(40):
        t.update(np.full((4, 3), 1e3), 500)  # huge forces: the rule asks for less than the floor
    assert t.alpha == pytest.approx(1e-7)


def test_forces_that_say_nothing_leave_alpha():
    t = AlphaTracker(1e-7, noise=1e-3)
    t.update(np.full((4, 3), 0.01), 500)
    a = t.alpha
    for g in (np.zeros((4, 3)), np.full((4, 3), np.nan), np.zeros((0, 3))):
        assert t.update(g, 500) == a


@pytest.mark.parametrize(
    "floor, noise, ceiling",
    [(1e-7, 0.0, 100), (1e-7, -1e-3, 100), (1e-7, float("nan"), 100), (0.0, 1e-3, 100), (1e-7, 1e-3, 0.5)],
)
def test_bad_settings_are_refused(floor, noise, ceiling):
    with pytest.raises(ValueError):
        AlphaTracker(floor, noise, ceiling=ceiling)

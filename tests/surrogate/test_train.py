"""The trainer's validation statistics (its training end to end is in test_build)."""

import numpy as np
import pytest
import torch
from scipy.stats import t as student_t

from service.surrogate.network import mlp
from service.surrogate.train import decay_groups, ratio_standard_error

from ..conftest import correlated_paths


def test_the_per_path_standard_errors_bound_holds_its_confidence_on_correlated_paths():
    """The relative error's standard error took every step of a load path for an independent
    sample, though a path's steps share its load: the one-sided 99 % lower bound of a validation
    over 5 paths of 6 steps left the truth below it in ~13 % of simulated validations. Over the
    paths it is near the nominal 1 %."""
    rng = np.random.default_rng(21)
    trials, paths, steps = 2000, 5, 6
    per_path = per_sample = 0
    t_path, t_sample = student_t.ppf(0.99, paths - 1), student_t.ppf(0.99, paths * steps - 1)
    for _ in range(trials):
        errors, sizes, path, truth = correlated_paths(rng, paths, steps)
        ratio = errors.sum() / sizes.sum()
        # the bound build.worse_at_least takes, on the log scale
        per_path += ratio * np.exp(-t_path * ratio_standard_error(errors, sizes, path) / ratio) > truth
        alone = ratio_standard_error(errors, sizes, np.arange(len(errors)))  # each sample its own path
        per_sample += ratio * np.exp(-t_sample * alone / ratio) > truth
    assert per_path / trials <= 0.02, per_path / trials
    assert per_sample / trials >= 0.08, per_sample / trials  # the old figure, far past its 1 %


def test_a_paths_repeated_steps_add_nothing_to_its_standard_error():
    """Steps that repeat one another carry no more information than one of them: over paths the
    figure is unchanged (the per-sample figure shrank by sqrt 2). Under two paths there is none."""
    errors, sizes, path, _ = correlated_paths(np.random.default_rng(3), 6, 4)
    once = ratio_standard_error(errors, sizes, path)
    twice = ratio_standard_error(np.repeat(errors, 2), np.repeat(sizes, 2), np.repeat(path, 2))
    assert once is not None and twice == pytest.approx(once, rel=1e-12)
    # each sample its own path is the textbook ratio-estimator figure, which the repeats shrink
    alone, repeated = (ratio_standard_error(e, s, np.arange(len(e))) for e, s in
                       ((errors, sizes), (np.repeat(errors, 2), np.repeat(sizes, 2))))  # fmt: skip
    assert repeated == pytest.approx(alone / np.sqrt(2), rel=0.05)
    one = path == 0
    assert ratio_standard_error(errors[one], sizes[one], path[one]) is None


def test_the_decay_shrinks_weight_matrices_and_spares_biases_and_prelu_slopes():
    """Decayed PReLU slopes sank to 6e-15, their gradients into subnormal floats that slowed late
    epochs 2x: the decay is the weight matrices' alone, and every parameter is in one group."""
    torch.manual_seed(0)
    net = mlp(4, [8], 3)
    groups = decay_groups(net, 0.5)
    assert sorted(id(p) for g in groups for p in g["params"]) == sorted(id(p) for p in net.parameters())
    before = {name: p.detach().clone() for name, p in net.named_parameters()}
    opt = torch.optim.Adam(groups, lr=1e-2)
    for _ in range(20):  # no data gradient: only the decay moves anything
        opt.zero_grad()
        (net(torch.zeros(1, 4)).sum() * 0.0).backward()
        opt.step()
    after = dict(net.named_parameters())
    assert after["0.weight"].detach().abs().sum() < 0.9 * before["0.weight"].abs().sum()
    for name in ("0.bias", "1.weight", "2.bias"):  # the first layer's bias, the PReLU's slopes, the last bias
        assert torch.equal(after[name].detach(), before[name]), name

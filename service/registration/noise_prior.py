"""The regularisation weight from the clouds' noise: the forces' MAP estimate under a prior the
stream estimates from its own frames.

Phi(g) = 1/(2m) sum_j d_j^2 + alpha/2 |g|^2, times m / sigma^2, is the negative log posterior of
the forces given m points with per-axis noise sigma (the normal component of the noise is what
the distance sees) and a zero-mean Gaussian prior of variance s^2 on each force component, when

    alpha = sigma^2 / (m s^2).

The prior's variance is unknown but a stream estimates it from the forces of its last frame,
as MacKay's evidence framework does (the fixed point of expectation-maximisation on it):
s^2 = |g|^2 / gamma, with gamma = sum_i l_i / (l_i + alpha) over the eigenvalues l_i of J's
Gauss-Newton Hessian in g, the number of force directions the cloud determines. The directions
it does not see hold the prior's value, zero, and say nothing of s: dividing |g|^2 by all K
components (the rule before, mean g^2) counted them, took s too small and alpha too large (on
the demo's calibration seeds, docs/performance.md). Without the Hessian (a model with no
Jacobian) gamma falls back to K. The rule needs no calibration to the organ: it scales with the
scene's loads.

Two guards. The bare rule has a collapse: smaller forces give a larger alpha, which gives smaller
forces (measured: alpha 8e10 on one sequence), so alpha stays within [floor, ceiling x floor],
the floor being the session's default (the right weight for clean clouds). And each frame moves
alpha to the geometric mean of its value and the rule's, so one odd frame does not throw it far.
What it gains, and where it loses, is measured in docs/performance.md ("Noisy clouds").
"""

from __future__ import annotations

import math

import numpy as np

Array = np.ndarray


class AlphaTracker:
    """alpha for the next frame of a stream whose clouds carry per-axis noise `noise` (m).

    Starts at `floor` (the session's default alpha) and stays within [floor, floor x ceiling].
    """

    def __init__(self, floor: float, noise: float, *, ceiling: float = 100.0) -> None:
        if not (math.isfinite(noise) and noise > 0):
            raise ValueError(f"noise must be a positive length, got {noise}")
        if not (math.isfinite(floor) and floor > 0):
            raise ValueError(f"floor must be a positive weight, got {floor}")
        if not ceiling >= 1.0:
            raise ValueError(f"ceiling must be at least 1, got {ceiling}")
        self.noise = float(noise)
        self.floor, self.top = float(floor), float(floor) * ceiling
        self.alpha = self.floor

    def rule(self, g: Array, m: int, gamma: float | None = None) -> float | None:
        """sigma^2 gamma / (m |g|^2), clamped; gamma defaults to g's size. None when the forces
        say nothing (all zero)."""
        e2 = float(np.sum(np.square(g))) if np.size(g) else 0.0
        n = float(np.size(g)) if gamma is None else float(gamma)
        if not (math.isfinite(e2) and e2 > 0 and m > 0 and math.isfinite(n) and n > 0):
            return None
        return min(max(self.noise * self.noise * n / (m * e2), self.floor), self.top)

    def update(self, g: Array, m: int, gamma: float | None = None) -> float:
        """Move alpha after a frame that ended at forces `g` (k, 3) on `m` points, with gamma
        force directions determined (see the module); returns it."""
        target = self.rule(g, m, gamma)
        if target is not None:
            self.alpha = math.sqrt(self.alpha * target)
        return self.alpha

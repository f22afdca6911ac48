"""Error against run time: sweep what trades one for the other and keep every point.

Knobs: the gradient tolerance and the iteration cap (both methods), the number of cloud points,
and the surrogate's size (every trained variant given). Each point is `passes` passes over the
same frames, each taking the same steps: mean TRE, mean resultant-force error, and the median
over warm frames of each frame's median time over the passes (one pass's times moved by up to
2x between two runs minutes apart on a shared machine); each pass's own median is kept too."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable

import numpy as np

from ..optional import need
from ..registration.session import SessionConfig
from .cases import Case, noisy, run_passes, summarise
from .liver import FEM, NETWORK

log = logging.getLogger(__name__)

NETWORK_GTOL = (3e-2, 1e-2, 3e-3, 1e-3, 3e-4, 2e-4, 1e-4, 3e-5, 1e-5)
#: around the default 1e-7: less bias on the forces of clean clouds, less robustness to noise
NETWORK_ALPHA = (1e-8, 3e-8, 3e-7, 1e-6)
#: the setting nearest all three liver targets at once (20 ms, 0.3 mm, 5 %), from the alpha
#: and gtol knobs, tried on every surrogate
TUNED = {"gtol": 2e-4, "alpha": 3e-8}
NETWORK_MAX_ITER = (3, 5, 10, 20, 40, 80)
FEM_GTOL = (1e-3, 1e-4, 3e-5, 1e-5)
#: the Newton method's tolerance with Levenberg-Marquardt (liver_part's second Newton row)
FEM_LM_GTOL = FEM_GTOL
#: the network's tolerance with Levenberg-Marquardt (liver_part's second network row)
LM_GTOL = (1e-2, 3e-3, 1e-3, 3e-4, 1e-4, 3e-5)
POINTS = (50, 100, 250, 500)


#: what one sweep point measures: (model, config, cloud points or None for all, whether on the
#: Newton method's shorter subset) -> mean TRE (mm), mean force error (%), median ms, mean
#: iterations, converged fraction, under the keys of a row
Score = Callable[[object, SessionConfig, "int | None", bool], dict]


def sweep(
    score: Score,
    network_model,
    fem_model,
    network: SessionConfig,
    fem: SessionConfig,
    *,
    gtols,
    caps,
    points,
    max_points: int,
    fem_gtols,
    alphas=(),
    variants: dict | None = None,
    tuned: dict | None = None,
    other_optimizer_gtols=(),
    fem_other_optimizer_gtols=(),
) -> list[dict]:
    """One row per knob setting, the same knobs for every scene: the gradient tolerance, the
    iteration cap and the regularisation weight (network), the cloud's size (up to
    `max_points`), the surrogate (each of `variants`, a name to another trained network; again
    at the `tuned` settings if given), the Newton method's tolerance, and the network's
    tolerance with the other optimizer (`other_optimizer_gtols`: L-BFGS-B and
    Levenberg-Marquardt, whichever `network` does not use; `fem_other_optimizer_gtols` the same
    for the Newton method). A row's method names its optimizer where it is not L-BFGS-B (the
    paper's)."""
    rows = []

    def row(knob, value, model, config, n=None, short=False):
        rows.append({"knob": knob, "value": value, "method": method_label(config), **score(model, config, n, short)})
        log.info("pareto %s", rows[-1])

    for gtol in gtols:
        row("gtol", gtol, network_model, dataclasses.replace(network, gtol=gtol, max_iter=max(network.max_iter, 500)))
    for cap in caps:
        row("max_iter", cap, network_model, dataclasses.replace(network, gtol=1e-6, max_iter=cap))
    for alpha in alphas:
        row("alpha", alpha, network_model, dataclasses.replace(network, alpha=alpha))
    for n in points:
        if n <= max_points:
            row("points", n, network_model, network, n)
    for name, model in (variants or {}).items():
        row("surrogate", name, model, network)
    if tuned:
        knob = "surrogate @ " + ", ".join(f"{k} {v:g}" for k, v in tuned.items())
        for name, model in (variants or {}).items():
            row(knob, name, model, dataclasses.replace(network, **tuned))
    for gtol in fem_gtols:
        row("gtol", gtol, fem_model, dataclasses.replace(fem, gtol=gtol), short=True)
    other = dataclasses.replace(network, optimizer=_other(network.optimizer))
    for gtol in other_optimizer_gtols:
        row("gtol", gtol, network_model, dataclasses.replace(other, gtol=gtol, max_iter=max(network.max_iter, 500)))
    for gtol in fem_other_optimizer_gtols:
        row("gtol", gtol, fem_model, dataclasses.replace(fem, optimizer=_other(fem.optimizer), gtol=gtol), short=True)
    return rows


def _other(optimizer: str) -> str:
    return "lbfgsb" if optimizer != "lbfgsb" else "levenberg-marquardt"


def method_label(config: SessionConfig) -> str:
    """The method, with the optimizer where it is not L-BFGS-B: 'network', 'fem',
    'network, levenberg-marquardt', 'fem, levenberg-marquardt'."""
    return config.method if config.optimizer == "lbfgsb" else f"{config.method}, {config.optimizer}"


def pareto_part(
    entry,
    case: Case,
    *,
    variants: dict | None = None,
    fem_frames: int = 6,
    gtols=NETWORK_GTOL,
    caps=NETWORK_MAX_ITER,
    points=POINTS,
    fem_gtols=FEM_GTOL,
    alphas=NETWORK_ALPHA,
    tuned: dict | None = TUNED,
    lm_gtols=LM_GTOL,
    fem_lm_gtols=FEM_LM_GTOL,
    passes: int = 3,
) -> list[dict]:
    """The liver's sweep over one recorded sequence (the Newton method on its first
    `fem_frames` frames), each point timed over `passes` passes."""
    short = dataclasses.replace(case, clouds=case.clouds[:fem_frames], positions=case.positions[:fem_frames],
                                net_forces=case.net_forces[:fem_frames])  # fmt: skip

    def score(model, config, n, is_short):
        records, each = run_passes(model, short if is_short else (noisy(case, points=n) if n else case), config, passes)
        s = summarise(records)
        return {"tre_mm": s["tre_mean_mm"], "force_error_pct": s["force_error_mean_pct"], "ms": s["ms_median"],
                "iterations": s["iterations_mean"], "converged": s["converged_fraction"],
                "ms_passes": each, "failed_frames": s["failed_frames"]}  # fmt: skip

    return sweep(score, entry.network, entry.fem, NETWORK, FEM, gtols=gtols, caps=caps, points=points,
                 max_points=min(len(c) for c in case.clouds), fem_gtols=fem_gtols, alphas=alphas, variants=variants,
                 tuned=tuned, other_optimizer_gtols=lm_gtols, fem_other_optimizer_gtols=fem_lm_gtols)  # fmt: skip


def pareto_front(rows: list[dict], error: str = "tre_mm") -> list[dict]:
    """The points no other point beats on both time and error, fastest first; none with a
    failed frame (its error is over the frames that did not fail: it cannot be ranked)."""
    pts = sorted((r for r in rows if not r.get("failed_frames")), key=lambda r: (r["ms"], r[error]))
    front, best = [], np.inf
    for r in pts:
        if r[error] < best:
            front.append(r)
            best = r[error]
    return front


def plot(rows: list[dict], path, title: str) -> None:
    matplotlib = need("matplotlib", "the benchmark's figures")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    markers = {"gtol": "o", "max_iter": "s", "points": "^", "surrogate": "D", "alpha": "v"}
    colours = {
        "network": "tab:blue",
        "network, levenberg-marquardt": "tab:green",
        "fem": "tab:red",
        "fem, levenberg-marquardt": "tab:purple",
    }
    for ax, key, label in (
        (axes[0], "tre_mm", "mean TRE (mm)"),
        (axes[1], "force_error_pct", "resultant-force error (%)"),
    ):
        for r in rows:
            marker = "*" if str(r["knob"]).startswith("surrogate @") else markers.get(r["knob"], "o")
            marker = "x" if r.get("failed_frames") else marker  # off the front: some frames failed
            ax.scatter(r["ms"], r[key], marker=marker, color=colours.get(r["method"], "k"), alpha=0.75)
        for method in colours:
            front = pareto_front([r for r in rows if r["method"] == method], key)
            if front:
                ax.plot(
                    [r["ms"] for r in front],
                    [r[key] for r in front],
                    color=colours[method],
                    lw=1,
                    label=f"{method}: Pareto front",
                )
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("milliseconds per frame (median, warm)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    for knob, m in markers.items():
        axes[0].scatter([], [], marker=m, color="grey", label=f"knob: {knob}")
    if any(r.get("failed_frames") for r in rows):
        axes[0].scatter([], [], marker="x", color="grey", label="failed frames (error over the rest)")
    if any(str(r["knob"]).startswith("surrogate @") for r in rows):
        axes[0].scatter([], [], marker="*", color="grey", label="knob: surrogate, tuned")
    axes[0].legend(fontsize=7, loc="upper right")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)

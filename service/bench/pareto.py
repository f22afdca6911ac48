"""Error against run time: sweep what trades one for the other and keep every point.

Knobs: the gradient tolerance and the iteration cap (both methods), the number of cloud points,
and the surrogate's size (every trained variant given). Each point is one pass over the same
frames: mean TRE, mean resultant-force error, median milliseconds per warm frame."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from .cases import Case, noisy, run_case, summarise
from .liver import FEM, NETWORK

log = logging.getLogger(__name__)

NETWORK_GTOL = (3e-2, 1e-2, 3e-3, 1e-3, 3e-4, 1e-4, 3e-5, 1e-5)
NETWORK_MAX_ITER = (3, 5, 10, 20, 40, 80)
FEM_GTOL = (1e-3, 1e-4, 3e-5, 1e-5)
POINTS = (50, 100, 250, 500)


def _row(knob: str, value, model, case: Case, config) -> dict:
    s = summarise(run_case(model, case, config))
    row = {"knob": knob, "value": value, "method": config.method, "tre_mm": s["tre_mean_mm"],
           "force_error_pct": s["force_error_mean_pct"], "ms": s["ms_median"],
           "iterations": s["iterations_mean"], "converged": s["converged_fraction"]}  # fmt: skip
    log.info("pareto %s", row)
    return row


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
) -> list[dict]:
    """One row per sweep point; `variants` maps a name to another trained network."""
    rows = []
    net, fem = entry.network, entry.fem
    for gtol in gtols:
        rows.append(_row("gtol", gtol, net, case, dataclasses.replace(NETWORK, gtol=gtol, max_iter=500)))
    for cap in caps:
        rows.append(_row("max_iter", cap, net, case, dataclasses.replace(NETWORK, gtol=1e-6, max_iter=cap)))
    for n in points:
        if n <= min(len(c) for c in case.clouds):
            rows.append(_row("points", n, net, noisy(case, points=n), NETWORK))
    for name, model in (variants or {}).items():
        rows.append(_row("surrogate", name, model, case, NETWORK))
    short = dataclasses.replace(case, clouds=case.clouds[:fem_frames], positions=case.positions[:fem_frames],
                                net_forces=case.net_forces[:fem_frames])  # fmt: skip
    for gtol in fem_gtols:
        rows.append(_row("gtol", gtol, fem, short, dataclasses.replace(FEM, gtol=gtol)))
    return rows


def pareto_front(rows: list[dict], error: str = "tre_mm") -> list[dict]:
    """The points no other point beats on both time and error, fastest first."""
    pts = sorted(rows, key=lambda r: (r["ms"], r[error]))
    front, best = [], np.inf
    for r in pts:
        if r[error] < best:
            front.append(r)
            best = r[error]
    return front


def plot(rows: list[dict], path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    markers = {"gtol": "o", "max_iter": "s", "points": "^", "surrogate": "D"}
    colours = {"network": "tab:blue", "fem": "tab:red"}
    for ax, key, label in ((axes[0], "tre_mm", "mean TRE (mm)"), (axes[1], "force_error_pct", "resultant-force error (%)")):
        for r in rows:
            ax.scatter(r["ms"], r[key], marker=markers.get(r["knob"], "o"), color=colours.get(r["method"], "k"), alpha=0.75)
        for method in ("network", "fem"):
            front = pareto_front([r for r in rows if r["method"] == method], key)
            if front:
                ax.plot([r["ms"] for r in front], [r[key] for r in front], color=colours[method], lw=1, label=f"{method}: Pareto front")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("milliseconds per frame (median, warm)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    for knob, m in markers.items():
        axes[0].scatter([], [], marker=m, color="grey", label=f"knob: {knob}")
    axes[0].legend(fontsize=7, loc="upper right")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)

"""The client side of ``elastreg demo``: stream a sequence whose answer is known, score each frame.

``service/demo.py`` starts the server and makes the sequence (the FEM gives the true shape of
every frame); this part needs only the client and arrays: it streams the clouds over the
WebSocket and prints, per frame, the registration error against the truth, the net-force error,
the client-side latency and the server's solve time, then a summary.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numpy as np

from .client import Stream


def _pct(a, q) -> float:
    return float(np.percentile(a, q)) if len(a) else float("nan")


def spearman(a: Sequence[float], b: Sequence[float]) -> float:
    """Spearman's rank correlation (no ties expected in measured floats)."""
    ra, rb = (np.argsort(np.argsort(np.asarray(x, float))) for x in (a, b))
    return float(np.corrcoef(ra, rb)[0, 1]) if len(ra) > 1 else float("nan")


#: what the demo's session returns: score_stream reads both
OUTPUTS = ("displacement", "forces")


def score_stream(
    stream: Stream,
    clouds: Sequence[np.ndarray],
    positions: Sequence[np.ndarray] | np.ndarray,
    net_forces: Sequence[np.ndarray] | np.ndarray,
    rest: np.ndarray,
    *,
    say: Callable[..., None] = print,
) -> int:
    """Stream `clouds` through an open `stream` (its session asked for OUTPUTS) and score each
    frame against the truth; 0 when done. The caller opens the stream first, so that its session
    can be watched from the first frame on.

    Shape: clouds[t] (m, 3); positions[t] (n, 3) the true node positions of frame t; net_forces[t]
    (3,) the true net force; rest (n, 3) the model's nodes.
    """
    say(f"{'frame':>5} {'error mm':>9} {'est. mm':>8} {'rest mm':>8} {'force %':>8} {'latency ms':>11} "
        f"{'solve ms':>9} {'iters':>6}  status")  # fmt: skip
    errors, rest_errors, force_errors, latency, solve, estimates, by_fem = [], [], [], [], [], [], 0
    failed = 0
    t_stream = time.perf_counter()
    for t, cloud in enumerate(clouds):
        t1 = time.perf_counter()
        r = stream.frame(cloud, frame_id=t)
        latency.append(1e3 * (time.perf_counter() - t1))
        truth = positions[t]
        err = 1e3 * np.linalg.norm(rest + r["displacement"] - truth, axis=1).mean()
        at_rest = 1e3 * np.linalg.norm(rest - truth, axis=1).mean()
        f_true = net_forces[t]
        f_err = 100 * np.linalg.norm(r["net_force"] - f_true) / max(np.linalg.norm(f_true), 1e-12)
        errors.append(err)
        rest_errors.append(at_rest)
        force_errors.append(f_err)
        solve.append(r["timing_ms"]["total"])
        failed += not r["converged"]
        est = r.get("error_estimate")
        estimates.append(np.inf if est is None else 1e3 * est)
        by_fem += r.get("method_used") == "fem"
        by = " (fem)" if r.get("method_used") == "fem" else ""
        say(f"{t + 1:>5} {err:>9.3f} {estimates[-1]:>8.3f} {at_rest:>8.3f} {f_err:>8.1f} {latency[-1]:>11.1f} "
            f"{solve[-1]:>9.1f} {r['iterations']:>6}  {r['status']}{by}")  # fmt: skip
    seconds = time.perf_counter() - t_stream
    n = len(errors)
    say(f"\n{n} frames in {seconds:.2f} s ({n / seconds:.1f} frames/s); {n - failed} converged")
    say(f"registration error: median {np.median(errors):.3f} mm, p95 {_pct(errors, 95):.3f} mm "
        f"(undeformed shape: median {np.median(rest_errors):.3f} mm)")  # fmt: skip
    say(f"net force error:    median {np.median(force_errors):.1f} %, "
        f"p95 {_pct(force_errors, 95):.1f} %")  # fmt: skip
    say(f"error estimate:     median {np.median(estimates):.3f} mm; rank correlation with the error "
        f"{spearman(estimates, errors):.2f}; {by_fem} of {n} frames corrected by the FEM")  # fmt: skip
    say(f"latency:            median {np.median(latency):.1f} ms, p95 {_pct(latency, 95):.1f} ms "
        f"(server solve: median {np.median(solve):.1f} ms, p95 {_pct(solve, 95):.1f} ms)")  # fmt: skip
    return 0

"""Where the network's Levenberg-Marquardt frames fold elements, and what keeping its trial
points off folded fields costs.

On the calibration draw (no report uses it), each frame of each site: its status, TRE, its
largest nodal error and force error, the number of inverted tets (det F <= 0) in its
displacement and how far their nodes lie from the support. Then the same sites with every
trial point whose whole field folds a tet refused as a forward failure (Levenberg-Marquardt
damps harder and tries again, as for any point the model cannot reach): if the fits need
folded fields, their TRE says so. One pass: errors, not times, are the point (the times are
kept, not compared).

    python benchmarks/folded_frames.py --model STORE/liver_paper --sites 6
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import calibration
import numpy as np

from service.bench.anysite import NETWORK_LM
from service.bench.cases import Case, score, stream_case
from service.fem.assembly import deformation_gradient
from service.fem.material import det3
from service.forward import ForwardFailed
from service.registration.confidence import estimator_for


class FoldRefused:
    """A network operator whose evaluations refuse forces whose whole field inverts a tet."""

    def __init__(self, op, model) -> None:
        self._op, self._energy = op, estimator_for(model).assembler.energy

    def __getattr__(self, name: str):
        return getattr(self._op, name)

    def __call__(self, g):
        out = self._op(g)
        if np.asarray(g).any() and not np.isfinite(self._energy(self._op.displacement(g))):
            raise ForwardFailed("forward_failed", "the field inverts elements")
        return out


class FoldRefusingModel:
    """The network model, its operators wrapped in :class:`FoldRefused`."""

    def __init__(self, model) -> None:
        self._model = model

    def __getattr__(self, name: str):
        return getattr(self._model, name)

    def restrict(self, support, nodes=None):
        return FoldRefused(self._model.restrict(support, nodes), self._model)


def frames(model, case: Case, variant: str) -> list[dict]:
    """Each frame of `case`: status, TRE, largest nodal error, force error, time, and its inverted tets."""
    mesh, out = case.mesh, []
    for k, (r, ms) in enumerate(stream_case(model, case, NETWORK_LM)):
        rec = score(case, k, r, ms, variant)
        u = r.outputs["displacement"]
        J = det3(deformation_gradient(u, mesh.tets, mesh.shape_gradients))
        bad = np.flatnonzero(~(J > 0))
        reach = 0.0
        if bad.size:
            nodes = mesh.nodes[np.unique(mesh.tets[bad])]
            gaps = np.linalg.norm(nodes[:, None] - mesh.nodes[case.support][None], axis=2).min(axis=1)
            reach = float(gaps.max() * 1e3)
        largest = float(np.linalg.norm(u - (case.positions[k] - mesh.nodes), axis=1).max() * 1e3)
        out.append({"frame": k, "status": r.status, "tre_mm": rec.tre_mm, "largest_error_mm": largest,
                    "force_error_pct": rec.force_error_pct,
                    "ms": ms, "evaluations": r.evaluations, "inverted_tets": int(bad.size),
                    "min_det_F": float(J.min()), "inverted_mm_from_support": reach})  # fmt: skip
    return out


def main() -> int:
    args = calibration.parser(__doc__, out="folded-frames/folded_frames.json").parse_args()
    entry, cases = calibration.cases(args)
    rows = []
    for case in cases:
        for variant, model in (("as is", entry.network), ("folds refused", FoldRefusingModel(entry.network))):
            recs = frames(model, case, variant)
            tre = float(np.mean([f["tre_mm"] for f in recs]))
            folded = sum(f["inverted_tets"] > 0 for f in recs)
            failed = sum(f["status"] != "converged" for f in recs)
            rows.append({"variant": variant, "case": case.name, "tre_mean_mm": tre, "frames": recs})
            print(f"{variant:>14} {case.name:>30}: TRE {tre:.4f} mm, {folded} frames folded, {failed} not converged")
    calibration.write(args, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

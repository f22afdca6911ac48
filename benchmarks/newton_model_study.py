"""The Newton method's Gauss-Newton model: its own dense Jacobian against the network's.

The anysite generator's calibration sites (CALIBRATION_SEED: no report uses them), each
registered by the Newton method with Levenberg-Marquardt at its default gtol, once as shipped
(du/dg from 3 solves per support node with the exact factor) and once with the network's
Jacobian at the same forces as the model. The evaluations, and so the exact gradient on the
step's right-hand side and the stopping test, are the FEM's in both: only the model differs.
Also the Newton method as auto's corrector (every frame corrected: max_error 1 nm), L-BFGS-B from
the network's registration. Prints and writes, per site and variant, the median warm-frame
time, the mean iterations and evaluations a warm frame, the mean TRE and the statuses.

    python benchmarks/newton_model_study.py --model /path/to/store/liver_paper
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import calibration

from service.bench.anysite import FEM, NETWORK
from service.bench.cases import run_case
from service.bench.machine import describe
from service.fem.model import FEMModel
from service.surrogate.model import NetworkModel

FEM_LM = dataclasses.replace(FEM, optimizer="levenberg-marquardt")


class _ModelOnly:
    """A Jacobian's products without its gradient image (that is the network's own gradient,
    not the FEM's)."""

    def __init__(self, jac) -> None:
        self.U, self._jac = jac.U, jac

    def gram_product(self, A):
        return self._jac.gram_product(A)

    def matvec(self, v):
        return self._jac.matvec(v)

    def rmatvec(self, w):
        return self._jac.rmatvec(w)


class _GuidedOperator:
    """The FEM's operator with the network's Jacobian as its Gauss-Newton model."""

    def __init__(self, fem_op, net_op) -> None:
        self.fem, self.net = fem_op, net_op
        self.support, self.nodes = fem_op.support, fem_op.nodes

    def __call__(self, g):
        return self.fem(g)

    def displacement(self, g):
        return self.fem.displacement(g)

    def reset(self) -> None:
        self.fem.reset()

    @property
    def deadline(self):
        return self.fem.deadline

    @deadline.setter
    def deadline(self, value) -> None:
        self.fem.deadline = value

    def jacobian(self, g):
        return _ModelOnly(self.net.jacobian(g))


@dataclasses.dataclass(frozen=True, eq=False)
class GuidedFEM:
    """A forward model: the FEM's physics, the network's Jacobian as the model."""

    fem: FEMModel
    network: NetworkModel
    method = "fem"

    @property
    def mesh(self):
        return self.fem.mesh

    @property
    def material(self):
        return self.fem.material

    @property
    def options(self):
        return self.fem.options

    def with_stiffness(self, E: float) -> GuidedFEM:
        return GuidedFEM(self.fem.with_stiffness(E), self.network.with_stiffness(E))

    def restrict(self, support, nodes=None) -> _GuidedOperator:
        return _GuidedOperator(self.fem.restrict(support, nodes), self.network.restrict(support, nodes))


def main() -> int:
    p = calibration.parser(
        __doc__, out="newton-model/newton_model.json", model_help="a whole-surface store entry with a reduced network"
    )
    args = p.parse_args()
    entry, cases = calibration.cases(args)
    corrector = dataclasses.replace(NETWORK, method="auto", max_error=1e-9)  # 1 nm: every frame
    variants = {
        "dense Jacobian (as shipped)": lambda case: run_case(entry.fem, case, FEM_LM),
        "the network's Jacobian": lambda case: run_case(GuidedFEM(entry.fem, entry.network), case, FEM_LM),
        "auto's corrector, every frame (L-BFGS-B)": lambda case: run_case(
            entry.network, case, corrector, corrector=entry.fem
        ),
    }
    rows = []
    for name, run in variants.items():
        for case in cases:
            recs = run(case)
            warm = recs[1:]
            rows.append(
                {
                    "variant": name,
                    "case": case.name,
                    "ms_median": float(np.median([r.ms for r in warm])),
                    "iterations_mean": float(np.mean([r.iterations for r in warm])),
                    "evaluations_mean": float(np.mean([r.evaluations for r in warm])),
                    "tre_mean_mm": float(np.nanmean([r.tre_mm for r in recs])),
                    "statuses": [r.status for r in recs],
                }
            )
            r = rows[-1]
            print(
                f"{name:42s} {case.name:28s} {r['ms_median']:9.0f} ms {r['iterations_mean']:6.1f} it "
                f"{r['evaluations_mean']:6.1f} ev {r['tre_mean_mm']:.4f} mm",
                flush=True,
            )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"machine": describe(), "model": args.model, "rows": rows}, indent=1))
    print(f"written to {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""What a network session pays when its support changes to a large one, by both routes to the
physics layout's linear block: the dense response and its SVD, and the randomised range finder
(service/surrogate/physics.py). Per route: the median restrict time over repeats, and the rank-r
block's 2-norm error over the first dropped singular value (1 is the SVD's optimum).

    python benchmarks/support_change.py --model model_store/phantom --repeats 3 \\
        --out reports/support-change/phantom.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

import service.surrogate.physics as physics
from service.bench.machine import describe
from service.config import limit_threads
from service.store import load_entry
from service.surrogate.model import NetworkOperator


def block(op: NetworkOperator) -> np.ndarray:
    """The operator's linear block as forces -> displacement: its basis columns times its rows."""
    r = physics.LINEAR_RANK
    return op._basis_all[:, -r:] @ op._skip[-r:].astype(np.float64)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, required=True)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    limit_threads(1)
    model = load_entry(args.model).network
    support = np.sort(model.region)
    exact = model.compliance().response(support) * model.stiffness_factor
    sv = np.linalg.svd(exact, compute_uv=False)
    routes: dict[str, dict] = {}
    out = {"machine": describe(), "model": str(args.model), "support_nodes": int(support.size), "routes": routes}
    for route, oversample in (("svd", 10**6), ("range finder", physics.OVERSAMPLE)):
        saved, physics.OVERSAMPLE = physics.OVERSAMPLE, oversample  # 10**6: the dense route
        try:
            times = []
            for _ in range(args.repeats):
                t = time.perf_counter()
                op = model.restrict(support)
                times.append(time.perf_counter() - t)
        finally:
            physics.OVERSAMPLE = saved
        error = np.linalg.norm(exact - block(op), 2) / sv[physics.LINEAR_RANK]
        routes[route] = {"restrict_s": statistics.median(times), "each_s": times, "error_over_optimum": error}
    text = json.dumps(out, indent=1)
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()

"""Network frames on a session's default support, the shipped phantom's whole load region (592
nodes), in process with one BLAS thread as the server runs: the frame time, its iterations and
its error against the synthetic truth, for L-BFGS-B (the default) and Levenberg-Marquardt, with
and without the clouds' noise declared.

    python benchmarks/region_frames.py [--store model_store] [--frames 8] [--repeats 3]

Prints a line per variant: warm frames' median time (the median over repeats of each repeat's
median), iterations and mean nodal error; the first frame (cold) is left out.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.bench.machine import describe
from service.config import limit_threads
from service.registration.session import Session
from service.registration.settings import SessionConfig
from service.store import load_entry
from service.synthetic import make_sequence, tool_patches

VARIANTS = {
    "L-BFGS-B": SessionConfig(),
    "L-BFGS-B, noise declared": SessionConfig(noise=1e-4),
    "Levenberg-Marquardt (gtol 3e-3)": SessionConfig(optimizer="levenberg-marquardt", gtol=3e-3),
    "Levenberg-Marquardt, noise declared": SessionConfig(optimizer="levenberg-marquardt", gtol=3e-3, noise=1e-4),
}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", default=str(ROOT / "model_store"))
    p.add_argument("--frames", type=int, default=8)
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args()
    limit_threads(1)
    entry = load_entry(Path(args.store) / "phantom")
    tool, _ = tool_patches(entry.mesh, entry.region)
    seq = make_sequence(
        entry.mesh, entry.fem.material, tool, n_frames=args.frames, peak_force=1.0, n_points=300, seed=0
    )
    m = describe()
    print(f"{m.get('cpu')}, commit {m.get('commit')}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    print(
        f"phantom, default support ({entry.region.size} nodes), {args.frames} frames of 300 points, "
        f"tool {tool.size} nodes"
    )
    for name, config in VARIANTS.items():
        times, iters, errors = [], [], []
        for _ in range(args.repeats):
            session, rep = Session(entry.model("network"), config), []
            for k, cloud in enumerate(seq.clouds):
                t0 = time.perf_counter()
                r = session.frame(cloud)
                if k:  # warm frames only
                    rep.append(1e3 * (time.perf_counter() - t0))
                    iters.append(r.iterations)
                    errors.append(np.linalg.norm(r.outputs["displacement"] - seq.displacements[k], axis=1).mean())
            times.append(float(np.median(rep)))
        print(
            f"  {name:38s} {np.median(times):6.1f} ms (repeats {', '.join(f'{t:.1f}' for t in times)}), "
            f"iterations {int(np.median(iters))} (median), error {1e3 * np.median(errors):.3f} mm (median)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Replay a registration-like stream on the paper's liver and time the point-to-surface distance.

Each frame k: ``bind`` the cloud of frame k; evaluate the objective at positions interpolating
between the true node positions of frames k - 1 and k (t = 0 at the warm start, t = 1 at the
answer), with line-search-like probes overshooting by 2-3 times the frame's motion and coming
back; then ``closest`` at the answer. The ``engine`` scenario adds what the registration engine
also asks for: first the rest state (the mesh's own positions, one evaluation), and ``closest``
at the warm start (its preconditioner). Prints the per-frame time (median and 90th percentile
over frames, each frame's time being its median over repeats) and the index builds per frame.

    python benchmarks/distance_bench.py                     # both backends
    python benchmarks/distance_bench.py --backend numba --repeats 9
    python benchmarks/distance_bench.py --module /tmp/distance_old.py   # another implementation

The machine may be shared: medians over repeats, and compare runs taken side by side.
"""

from __future__ import annotations

import argparse
import importlib.util
import itertools
import sys
import time
from pathlib import Path

import meshio
import numpy as np

from service.mesh import TetMesh

LIVER = Path(__file__).resolve().parents[2] / "shared" / "meshes" / "liver_paper"  # ../shared
SEQUENCE = LIVER / "sequences/neohookean/s1"
#: The evaluations of one frame, as interpolation parameters between frames k - 1 (0) and k (1):
#: three probes overshoot by 2-3 times the frame's motion, then the search comes back.
STEPS = (0.0, 2.5, 0.6, 0.85, 3.0, 0.95, 1.0, 2.0, 1.0, 1.0)


def load_module(path: str | None):
    if path is None:
        from service.registration import distance

        return distance
    spec = importlib.util.spec_from_file_location("distance_under_test", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def load_stream(n_frames: int):
    mesh = meshio.read(LIVER / "liver.msh")
    rest = np.asarray(TetMesh(mesh.points, mesh.cells_dict["tetra"]).nodes)
    matching = np.load(LIVER / "matching-triangles.npy")
    positions = np.load(SEQUENCE / "positions-default.npy")[:n_frames]
    clouds = [np.loadtxt(SEQUENCE / f"pointclouds/pc{k:02d}.txt") for k in range(len(positions))]
    return matching, rest, positions, clouds


def replay(S, rest, positions, clouds, frames, engine):
    """Time each frame of the stream once. Returns wall and CPU seconds (n,) each, builds (n,).

    CPU time is this thread's (``time.thread_time``): on a shared machine it leaves out the
    time the thread waited for a core, which wall time does not.
    """
    seconds, cpu, builds = [], [], []
    P = positions[:, S.nodes]
    x_rest = np.ascontiguousarray(rest[S.nodes])
    for k in frames:
        x0, x1 = P[k - 1], P[k]
        xs = [x0 + t * (x1 - x0) for t in STEPS]
        n0 = S.n_builds
        t0, c0 = time.perf_counter(), time.thread_time()
        S.bind(clouds[k])
        if engine:
            S(x_rest)
        for i, x in enumerate(xs):
            S(x)
            if engine and i == 0:
                S.closest(x)
        S.closest(x1)
        seconds.append(time.perf_counter() - t0)
        cpu.append(time.thread_time() - c0)
        builds.append(S.n_builds - n0)
    return np.array(seconds), np.array(cpu), np.array(builds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", choices=["numba", "numpy", "both"], default="both")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--frames", type=int, default=50)
    parser.add_argument("--module", help="a distance.py to time instead of the package's")
    parser.add_argument("--options", default="", help="PointToSurface keywords, k=v,k=v")
    parser.add_argument("--scenario", choices=["brief", "engine", "both"], default="both")
    args = parser.parse_args()
    module = load_module(args.module)
    options = {}
    for item in filter(None, args.options.split(",")):
        key, value = item.split("=")
        options[key] = float(value) if value.replace(".", "").replace("e-", "").isdigit() else value
    matching, rest, positions, clouds = load_stream(args.frames)
    frames = range(1, len(positions))
    backends = ["numba", "numpy"] if args.backend == "both" else [args.backend]
    scenarios = ["brief", "engine"] if args.scenario == "both" else [args.scenario]
    print(
        f"{args.module or 'service.registration.distance'}; {len(matching)} triangles, "
        f"{len(clouds[1])} points, {len(STEPS)} evaluations + closest per frame"
    )
    for scenario, backend in itertools.product(scenarios, backends):
        runs = []
        for _ in range(args.repeats + 1):  # the first pass warms caches up and is dropped
            S = module.PointToSurface(matching, backend=backend, **options)
            runs.append(replay(S, rest, positions, clouds, frames, scenario == "engine"))
        wall, cpu, builds = (np.array(z) for z in zip(*runs[1:], strict=True))
        builds = builds[-1]
        extra = ""
        if hasattr(S, "n_layouts"):
            extra = f" ({S.n_one_off / len(frames):.2f} one-off); layouts {S.n_layouts} in all"
        label = f"{scenario:6s} {backend:6s}"
        for name, t in (("wall", wall), ("cpu", cpu)):
            per_frame = 1e3 * np.median(t, axis=0)  # (frames,) ms, each the median of repeats
            print(
                f"{label} {name:4s} per frame: median {np.median(per_frame):6.2f} ms, "
                f"p90 {np.percentile(per_frame, 90):6.2f} ms, max {per_frame.max():6.2f} ms"
            )
        print(f"{label} builds per frame: mean {builds.mean():.2f}, max {builds.max()}{extra}")


if __name__ == "__main__":
    main()

"""Benchmark cases: registration sequences with known answers, and the runner that scores them.

A case is what the paper scores: a mesh, a support (where the registration may put forces), a
matching surface, and frames with their clouds, true node positions and true resultant force.
The runner streams a case through a :class:`~service.registration.session.Session` and records,
per frame, the mean target registration error over all nodes (mm), the resultant-force error
(%), the wall time (ms) and the optimiser's counts.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import io
import logging
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ..fem.material import NeoHookean
from ..mesh import TetMesh
from ..registration.session import FrameResult, Session, SessionConfig
from ..synthetic import make_sequence, perturb

log = logging.getLogger(__name__)

Array = np.ndarray

#: where ../shared sits beside the checkout (the paper's liver and its sequence)
SHARED = Path(__file__).resolve().parents[3] / "shared"
LIVER = SHARED / "meshes" / "liver_paper"
#: its recorded Neo-Hookean sequence, the one the paper reports
PAPER_SEQUENCE = LIVER / "sequences" / "neohookean" / "s1"


@dataclasses.dataclass
class Case:
    """Shape: positions (T, n, 3), net_forces (T, 3), clouds T x (m, 3), support (k,),
    matching (f, 3) node-id triangles or None (the whole boundary)."""

    name: str
    mesh: TetMesh
    support: Array
    matching: Array | None
    clouds: list[Array]
    positions: Array
    net_forces: Array

    @property
    def frames(self) -> int:
        return len(self.clouds)

    def with_clouds(self, clouds: list[Array], name: str | None = None) -> Case:
        return dataclasses.replace(self, clouds=clouds, name=name or self.name)


@dataclasses.dataclass
class FrameRecord:
    case: str
    method: str
    frame: int
    tre_mm: float
    force_error_pct: float
    ms: float
    iterations: int
    evaluations: int
    status: str
    converged: bool
    finite: bool  # no NaN or infinity anywhere in the result
    alpha: float | None = None  # the regularisation weight the frame ran with
    error_estimate_mm: float | None = None  # the frame's own estimate of its error
    method_used: str | None = None  # the forward model that answered (method auto)
    force_along_pct: float | None = None  # the answer's net force along the true one, % of it
    objective: float | None = None  # J at the answer (m^2), without the regulariser


@functools.cache
def liver_paper_mesh() -> TetMesh:
    """The paper's liver, its Dirichlet nodes fixed but node 756 (free in its sequences)."""
    import meshio

    with contextlib.redirect_stdout(io.StringIO()):  # meshio prints a blank line reading gmsh 2.2
        raw = meshio.read(LIVER / "liver.msh")
    fixed = np.load(LIVER / "dirichlet-vertices.npy")
    mesh, _ = TetMesh.build(raw.points, raw.cells_dict["tetra"], fixed[fixed != 756])
    return mesh


def liver_paper_support() -> Array:
    """The recorded sequence's support: where its registration may put forces. Shape: (k,)."""
    return np.load(PAPER_SEQUENCE / "forces-vertices-default.npy").astype(np.int64)


def liver_data_missing() -> str | None:
    """Why the paper's liver cannot be read (../shared is not beside the checkout), or None."""
    if not (LIVER / "liver.msh").exists():
        return f"the paper's liver is not in {LIVER} (../shared beside the checkout)"
    return None


def not_on_paper_liver(mesh: TetMesh, region: Array) -> str | None:
    """What a model on `mesh` with load region `region` lacks for the cases on the paper's liver
    (they name its nodes), or None: the liver's data, the liver's nodes, the sequence's support."""
    if missing := liver_data_missing():
        return missing
    liver = liver_paper_mesh()
    if mesh.n_nodes != liver.n_nodes or not np.allclose(mesh.nodes, liver.nodes):
        return f"its mesh ({mesh.n_nodes} nodes) is not the paper's liver ({liver.n_nodes} nodes)"
    outside = np.setdiff1d(liver_paper_support(), region)
    if outside.size:
        return f"its load region lacks {outside.size} of the recorded sequence's support nodes"
    return None


def liver_paper_case() -> Case:
    """The paper's liver and its recorded Neo-Hookean sequence (shared/meshes/liver_paper)."""
    seq = PAPER_SEQUENCE
    clouds = [np.loadtxt(seq / "pointclouds" / f"pc{k:02d}.txt") for k in range(50)]
    return Case(
        name="liver s1 (paper)",
        mesh=liver_paper_mesh(),
        support=liver_paper_support(),
        matching=np.load(LIVER / "matching-triangles.npy").astype(np.int64),
        clouds=clouds,
        positions=np.load(seq / "positions-default.npy"),
        net_forces=np.load(seq / "true-forces.npy"),
    )


def held_out(entry, support: Array) -> str:
    """How much of a case's `support` the entry's build kept every training load off ([training]
    keep_off, read from its manifest): "held out" for all of it, "N of M support nodes held
    out" for part, "" for none (a build without keep_off: its sites lie inside what it learnt)."""
    kept = entry.manifest.get("training", {}).get("load_distribution", {}).get("keep_off", [])
    n = int(np.isin(support, np.asarray(kept, np.int64)).sum())
    if n == 0:
        return ""
    return "held out" if n == len(support) else f"{n} of {len(support)} support nodes held out"


def synthetic_case(
    name: str,
    mesh: TetMesh,
    material: NeoHookean,
    tool: Array,
    support: Array,
    *,
    matching: Array | None = None,
    frames: int = 20,
    peak_force: float = 1.0,
    n_points: int = 500,
    seed: int = 0,
    **kwargs,
) -> Case:
    """A sequence made the way the paper made its own: a local force grows on `tool`, the FEM
    gives each frame, a camera sees part of the deformed surface."""
    seq = make_sequence(
        mesh, material, tool, n_frames=frames, peak_force=peak_force, n_points=n_points, seed=seed, **kwargs
    )
    return Case(name, mesh, np.asarray(support, np.int64), matching, seq.clouds, seq.positions, seq.net_forces)


def noisy(case: Case, noise: float = 0.0, outliers: float = 0.0, points: int | None = None, seed: int = 0) -> Case:
    """The same frames with noisy, outlier-ridden or thinned clouds."""
    rng = np.random.default_rng(seed)
    clouds = []
    for c in case.clouds:
        if points is not None and points < len(c):
            c = c[rng.choice(len(c), size=points, replace=False)]
        clouds.append(perturb(c, rng, noise, outliers, spread=0.02))
    return case.with_clouds(clouds)


def stream_case(model, case: Case, config: SessionConfig, corrector=None) -> Iterator[tuple[FrameResult, float]]:
    """Every frame of `case` through one session (`corrector`: the FEM for method auto), with
    its displacement and forces asked for: each frame's result and wall time (ms)."""
    config = dataclasses.replace(
        config,
        support=tuple(int(i) for i in case.support),
        matching=None if case.matching is None else tuple(map(tuple, case.matching.tolist())),
        outputs=("displacement", "forces"),
    )
    session = Session(model, config, corrector)
    for k, cloud in enumerate(case.clouds):
        t0 = time.perf_counter()
        r = session.frame(cloud, frame_id=k)
        yield r, 1e3 * (time.perf_counter() - t0)


def score(case: Case, k: int, r: FrameResult, ms: float, method: str) -> FrameRecord:
    """Frame `k`'s result against the case's truth: TRE over all nodes, resultant-force error."""
    u = r.outputs.get("displacement")
    finite = bool(u is not None and np.isfinite(u).all() and np.isfinite(r.net_force).all())
    tre = (
        float(np.linalg.norm(case.mesh.nodes + u - case.positions[k], axis=1).mean() * 1e3) if finite else float("nan")
    )
    true_f = case.net_forces[k]
    size = max(float(np.linalg.norm(true_f)), 1e-300)
    fe = float(np.linalg.norm(r.net_force - true_f) / size * 100)
    along = float(r.net_force @ true_f / size / size * 100)  # under 100: the prior's shrinkage
    est = 1e3 * r.error_estimate if np.isfinite(r.error_estimate) else float("inf")
    return FrameRecord(
        case.name,
        method,
        k,
        tre,
        fe,
        ms,
        r.iterations,
        r.evaluations,
        r.status,
        r.converged,
        finite,
        r.alpha,
        est,
        r.method_used,
        along,
        r.objective,
    )


def run_case(model, case: Case, config: SessionConfig, method: str | None = None, corrector=None) -> list[FrameRecord]:
    """Stream every frame of `case` through one session (stream_case); score each frame."""
    return [
        score(case, k, r, ms, method or model.method)
        for k, (r, ms) in enumerate(stream_case(model, case, config, corrector))
    ]


def same_steps(run: Callable[[], list], passes: int, steps: Callable[[Any], int], what: str) -> list[list]:
    """`run()` `passes` times, refused unless every pass took the first one's steps (``steps``
    of each record): timing over passes only means something if the work was the same, and
    what differs between them is then the machine (a shared one moves single passes by up to
    2x)."""
    if passes < 1:
        raise ValueError(f"passes must be at least 1, got {passes}")
    runs = [run() for _ in range(passes)]
    first = [steps(r) for r in runs[0]]
    if any([steps(r) for r in other] != first for other in runs[1:]):
        raise RuntimeError(f"{what}: the passes took different steps: registration is not deterministic")
    return runs


def run_passes(
    model, case: Case, config: SessionConfig, passes: int, method: str | None = None
) -> tuple[list[FrameRecord], list[float]]:
    """run_case() `passes` times (same_steps): the first pass's records, each frame's time its
    median over the passes, and each pass's median warm-frame time."""
    runs = same_steps(lambda: run_case(model, case, config, method), passes, lambda r: r.iterations, case.name)
    records = [dataclasses.replace(r, ms=float(np.median([run[i].ms for run in runs]))) for i, r in enumerate(runs[0])]
    return records, [summarise(run)["ms_median"] for run in runs]


def rest_baseline(case: Case) -> list[FrameRecord]:
    """No registration: the rest shape and no force."""
    out = []
    for k in range(case.frames):
        tre = float(np.linalg.norm(case.positions[k] - case.mesh.nodes, axis=1).mean() * 1e3)
        out.append(FrameRecord(case.name, "none (rest shape)", k, tre, 100.0, 0.0, 0, 0, "-", True, True))
    return out


def summarise(records: list[FrameRecord], skip_first: bool = True, passes: list[float] | None = None) -> dict:
    """Medians and means over frames; time over warm frames (the first is a cold start).
    `passes`: each pass's median time (run_passes), kept as ``ms_median_passes``. A failed frame
    (a NaN or infinity in its answer) has no error to average: the means and medians are over
    the others, ``failed_frames`` counts it and the worst frame's TRE is infinite."""
    if not records:
        return {}
    tre = np.array([r.tre_mm for r in records])
    fe = np.array([r.force_error_pct for r in records])
    failed = sum(not r.finite or not np.isfinite(r.tre_mm) for r in records)
    warm = records[1:] if skip_first and len(records) > 1 else records
    ms = np.array([r.ms for r in warm])
    return {
        "case": records[0].case,
        "method": records[0].method,
        "frames": len(records),
        "tre_mean_mm": float(np.nanmean(tre)),
        "tre_median_mm": float(np.nanmedian(tre)),
        "tre_max_mm": float("inf") if failed else float(np.max(tre)),
        "failed_frames": failed,
        "force_error_mean_pct": float(np.nanmean(fe)),
        "force_error_median_pct": float(np.nanmedian(fe)),
        "ms_median": float(np.median(ms)),
        "ms_p90": float(np.percentile(ms, 90)),
        "ms_mean": float(ms.mean()),
        "ms_std": float(ms.std()),
        "iterations_mean": float(np.mean([r.iterations for r in records])),
        "iterations_std": float(np.std([r.iterations for r in records])),
        "converged_fraction": float(np.mean([r.converged for r in records])),
        "all_finite": bool(all(r.finite for r in records)),
        "statuses": sorted({r.status for r in records}),
    } | ({"ms_median_passes": passes} if passes is not None else {})

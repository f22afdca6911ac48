"""The shipped model store: every entry loads through the store and registers frames whose
answer is known (made by the FEM from a known load), within its documented accuracy."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.registration.session import Session, SessionConfig
from service.store import open_store
from service.synthetic import make_sequence

STORE = Path(__file__).resolve().parents[1] / "model_store"
SHIPPED = ("beam", "phantom")


@pytest.fixture(scope="module")
def shipped():
    entries, errors = open_store(STORE)
    assert errors == {}, errors
    assert set(SHIPPED) <= set(entries), sorted(entries)
    return entries


def _patch(entry, size: int) -> np.ndarray:
    """``size`` free surface nodes of the load region nearest the region's surface centroid."""
    mesh = entry.mesh
    cand = np.intersect1d(mesh.free_surface_nodes, entry.region)
    x = mesh.nodes[cand]
    centre = int(cand[np.argmin(np.linalg.norm(x - x.mean(axis=0), axis=1))])
    near = mesh.surface_patch(centre, 3 * size)
    return np.sort(near[np.isin(near, entry.region)][:size])


@pytest.mark.parametrize("name", SHIPPED)
def test_a_shipped_model_registers_a_known_deformation(shipped, name):
    entry = shipped[name]
    m = entry.manifest
    assert m["id"] == name and m["training"]["validation"]["mean_mm"] < 1.0
    tool, support = _patch(entry, 8), _patch(entry, 30)
    peak = 0.5 * float(m["scene"]["training"]["max_force"])
    seq = make_sequence(entry.mesh, entry.fem.material, tool, n_frames=4, peak_force=peak, n_points=600, seed=3)
    assert len(seq.clouds) == 4  # the FEM followed the whole load
    session = Session(entry.network, SessionConfig(support=tuple(int(i) for i in support), outputs=("displacement",)))
    for cloud in seq.clouds:
        r = session.frame(cloud)
    truth = seq.positions[-1]
    moved = np.linalg.norm(truth - entry.mesh.nodes, axis=1).mean()
    tre = np.linalg.norm(entry.mesh.nodes + r.outputs["displacement"] - truth, axis=1).mean()
    f_true, f = seq.forces[-1].sum(0), r.net_force
    angle = np.degrees(np.arccos(f @ f_true / (np.linalg.norm(f) * np.linalg.norm(f_true))))
    print(
        f"{name}: mean displacement {1e3 * moved:.2f} mm, TRE {1e3 * tre:.3f} mm, "
        f"net force {np.linalg.norm(f) / np.linalg.norm(f_true):.2f} x the true one, {angle:.1f} degrees off"
    )
    assert r.converged and r.status == "converged"
    assert moved > 1e-3  # a real deformation (over a millimetre on average)
    # within the entry's own validation error, and a small part of the motion
    assert 1e3 * tre < m["training"]["validation"]["mean_mm"] and tre < 0.2 * moved
    # the resultant force, seen through part of the surface only: its size and direction
    assert 0.7 < np.linalg.norm(f) / np.linalg.norm(f_true) < 1.3 and angle < 30

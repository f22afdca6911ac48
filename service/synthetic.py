"""Synthetic registration sequences with known answers, made the way the paper made its own:
a local force on a few surface nodes grows and turns over the frames, the FEM gives the true
deformation of each frame, and each frame's cloud samples the part of the deformed surface a
camera would see (optionally with noise and outliers).

Used by the demo, the benchmark and the tests: every frame carries its true displacement and
true forces, so registration error and force error can be scored.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .fem.material import NeoHookean
from .fem.model import FEMModel
from .forward import ForwardFailed
from .mesh import TetMesh

Array = np.ndarray


@dataclasses.dataclass
class Sequence:
    """Shape: positions (T, n, 3) true node positions, forces (T, k, 3) on `tool` (k,),
    clouds: list of T (m_t, 3) arrays; visible (f,) the matching triangles (face ids)."""

    mesh: TetMesh
    tool: Array
    forces: Array
    positions: Array
    clouds: list[Array]
    visible_faces: Array  # frames stop early (fewer than asked) if the FEM cannot follow

    @property
    def displacements(self) -> Array:
        return self.positions - self.mesh.nodes[None]

    @property
    def net_forces(self) -> Array:
        return self.forces.sum(axis=1)


def visible_faces(mesh: TetMesh, view: Array, max_angle_deg: float = 75.0) -> Array:
    """Boundary faces whose outward normal faces the camera direction `view` (3,)."""
    v = np.asarray(view, float)
    v = v / np.linalg.norm(v)
    return np.flatnonzero(mesh.face_normals @ v >= np.cos(np.radians(max_angle_deg)))


def sample_surface(nodes: Array, faces: Array, n_points: int, rng: np.random.Generator) -> tuple[Array, Array, Array]:
    """Points uniformly distributed over the area of `faces` at node positions `nodes`.

    Shape: nodes (n, 3), faces (f, 3) -> points (m, 3), face index (m,), barycentric (m, 3).
    """
    x = nodes[faces]
    area = 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)
    face = rng.choice(len(faces), size=n_points, p=area / area.sum())
    r1, r2 = rng.random(n_points), rng.random(n_points)
    s = np.sqrt(r1)
    bary = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    return np.einsum("mk,mkd->md", bary, x[face]), face, bary


def perturb(
    points: Array, rng: np.random.Generator, noise: float = 0.0, outliers: float = 0.0, spread: float = 0.0
) -> Array:
    """Gaussian noise (std `noise`, m) and a fraction of outliers scattered within `spread` of
    the cloud's bounding box."""
    p = points + rng.normal(scale=noise, size=points.shape) if noise > 0 else points.copy()
    n_out = int(round(outliers * len(p)))
    if n_out:
        lo, hi = p.min(0) - spread, p.max(0) + spread
        idx = rng.choice(len(p), size=n_out, replace=False)
        p[idx] = rng.uniform(lo, hi, size=(n_out, 3))
    return p


def make_sequence(
    mesh: TetMesh,
    material: NeoHookean,
    tool: Array,
    *,
    n_frames: int = 20,
    peak_force: float = 1.0,
    direction: Array | None = None,
    turn_deg: float = 30.0,
    view: Array | None = None,
    n_points: int = 500,
    noise: float = 0.0,
    outliers: float = 0.0,
    seed: int = 0,
    shares: Array | None = None,
    fem: FEMModel | None = None,
) -> Sequence:
    """A load that grows linearly to `peak_force` (N, total, spread over `tool` by `shares`,
    evenly by default) while its direction turns by `turn_deg`; each frame's cloud samples the
    faces visible from `view`. `fem` solves it (default: linear tets on `mesh`).

    The default direction is the outward normal of the tool patch (a grasper pulling) and the
    default view looks at the patch (the camera sees where the tool acts).
    """
    rng = np.random.default_rng(seed)
    tool = np.asarray(tool, np.int64)
    normal = mesh.patch_normal(tool)
    d0 = normal if direction is None else np.asarray(direction, float) / np.linalg.norm(direction)
    axis = np.cross(d0, rng.normal(size=3))
    axis /= np.linalg.norm(axis)
    view = normal if view is None else np.asarray(view, float)
    faces_visible = visible_faces(mesh, view)
    op = (fem or FEMModel(mesh, material)).restrict(tool)
    forces, positions, clouds = [], [], []
    for t in range(n_frames):
        s = (t + 1) / n_frames
        angle = np.radians(turn_deg) * s
        d = d0 * np.cos(angle) + np.cross(axis, d0) * np.sin(angle)
        if shares is None:
            g = np.tile(d * (peak_force * s / tool.size), (tool.size, 1))
        else:
            g = np.asarray(shares, float)[:, None] * (d * (peak_force * s))
        try:
            x = mesh.nodes + op.displacement(g)  # warm-starts from the previous frame
        except ForwardFailed:
            break
        pts, _, _ = sample_surface(x, mesh.surface_faces[faces_visible], n_points, rng)
        forces.append(g)
        positions.append(x)
        clouds.append(perturb(pts, rng, noise, outliers, spread=0.02))
    return Sequence(mesh, tool, np.array(forces), np.array(positions), clouds, faces_visible)


def tool_patches(mesh: TetMesh, region: Array, tool_nodes: int = 12, support_nodes: int = 36) -> tuple[Array, Array]:
    """A tool patch and a larger support around it, both free surface nodes in `region`.

    The centre is the region's surface node nearest the region's surface centroid, so both
    patches grow inside the part of the surface the network was trained to load.
    """
    inside = np.zeros(mesh.n_nodes, bool)
    inside[region] = True
    cand = mesh.free_surface_nodes[inside[mesh.free_surface_nodes]]
    if cand.size == 0:
        raise ValueError("the model's load region has no free surface nodes")
    x = mesh.nodes[cand]
    centre = int(cand[np.argmin(np.linalg.norm(x - x.mean(axis=0), axis=1))])
    tool = mesh.surface_patch(centre, 3 * tool_nodes)  # nearest first: keep the closest in the region
    support = mesh.surface_patch(centre, support_nodes)
    return np.sort(tool[inside[tool]][:tool_nodes]), np.sort(support[inside[support]])

"""What a session takes in, checked before anything changes: its configuration, its matching
faces, each frame's cloud and support (a bad one is a one-line ValueError); and the support a
session takes where none is given."""

from __future__ import annotations

import numpy as np

from ..forward import ForwardModel, check_support
from ..mesh import TetMesh
from .reach import Box, check_reach
from .settings import METHODS, OUTPUT_NAMES, SessionConfig

Array = np.ndarray

#: a matching triangle whose area is under this share of its edges' squares lies on a line (at
#: rounding, 1e-16, from a collinear one; a sliver of a real surface mesh is far above it)
FLAT_FACE = 1e-12


def check_config(config: SessionConfig, corrector: ForwardModel | None) -> None:
    """The method, method auto's max_error and `corrector` (the FEM), and the outputs asked for."""
    if config.method not in METHODS:
        raise ValueError(f"unknown method {config.method!r}; choose from {list(METHODS)}")
    if config.method == "auto":
        if config.max_error is None:
            raise ValueError("method 'auto' needs max_error (m): the estimate past which the FEM corrects a frame")
        if corrector is None:
            raise ValueError("method 'auto' needs the FEM to correct with")
    elif config.max_error is not None:
        raise ValueError("max_error applies to method 'auto' only")
    unknown = set(config.outputs) - set(OUTPUT_NAMES)
    if unknown:
        raise ValueError(f"unknown outputs {sorted(unknown)}; choose from {list(OUTPUT_NAMES)}")


def check_faces(mesh: TetMesh, faces) -> Array:
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError("matching must be a non-empty list of node-id triples")
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError("matching node ids must be integers")
    if f.min() < 0 or f.max() >= mesh.n_nodes:
        raise ValueError(f"matching node ids must lie in 0..{mesh.n_nodes - 1}")
    f = f.astype(np.int64)
    # a triangle without area has no normal: every frame's distance, so its estimate, was not finite
    repeats = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    if repeats.any():
        i = int(np.argmax(repeats))
        raise ValueError(f"matching face {i} {f[i].tolist()} repeats a node: a triangle needs three distinct nodes")
    ab, ac = mesh.nodes[f[:, 1]] - mesh.nodes[f[:, 0]], mesh.nodes[f[:, 2]] - mesh.nodes[f[:, 0]]
    twice_area = np.linalg.norm(np.cross(ab, ac), axis=1)
    flat = twice_area <= FLAT_FACE * (np.einsum("ij,ij->i", ab, ab) + np.einsum("ij,ij->i", ac, ac))
    if flat.any():
        i = int(np.argmax(flat))
        raise ValueError(f"matching face {i} {f[i].tolist()} has no area at rest: its three nodes lie on one line")
    return f


def check_frame(mesh: TetMesh, box: Box, points, support) -> tuple[Array, Array | None]:
    """A frame's cloud as (m, 3) float64 and its support's node ids (None: the session's),
    or a one-line ValueError: a bad shape, a value not finite, a cloud past the model's reach
    (`box`, reach.py), a support this mesh cannot take."""
    points = np.asarray(points, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"points must be a non-empty (m, 3) array, got shape {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("points contain NaN or infinite values")
    check_reach(box, points)
    return points, None if support is None else check_support(mesh, np.asarray(support))


def default_support(model: ForwardModel) -> Array:
    """Every node the model can put a force on: its load region, or the free surface."""
    region = getattr(model, "region", None)
    return np.asarray(region if region is not None else model.mesh.free_surface_nodes, np.int64)

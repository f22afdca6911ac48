"""A scene's node sets: id files read, the file's ids mapped onto the mesh's numbering, and the
fixed nodes, load region, support and matching triangles its tables name.

Node ids in a scene are the file's ids; when loading drops unused nodes they are mapped onto the
mesh's numbering (`loaded`, the record of loading; without one the ids are the mesh's). Errors
name the scene's `origin` and the key (:func:`~service.scene.errors.scene_error`).
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ..mesh import TetMesh
from ..meshfile import LoadedMesh
from .errors import scene_error
from .tables import BoundarySpec, RegistrationSpec, TrainingSpec

log = logging.getLogger("service.scene")  # a scene's warnings under one name, whichever module finds them

Array = np.ndarray


def read_ids(path: Path, key: str, origin: str) -> Array:
    """A scene's id file (:func:`read_node_ids`), its errors naming the scene's key."""
    try:
        return read_node_ids(path)
    except ValueError as exc:
        raise scene_error(origin, key, str(exc)) from exc


def read_node_ids(path: Path, *, several_a_line: bool = False) -> Array:
    """Node ids from a .npy int array, or a text file with one id a line (any number a line,
    whitespace-separated, with ``several_a_line``): '#' comments, and a UTF-8 BOM, which Windows
    editors write, skipped. ValueError, one line naming the file, where it holds no such ids."""
    try:
        if path.suffix == ".npy":
            ids = np.load(path, allow_pickle=False)
        elif several_a_line:
            lines = path.read_text(encoding="utf-8-sig").splitlines()
            ids = np.array([w for line in lines for w in line.split("#", 1)[0].split()], np.int64)
        else:
            with warnings.catch_warnings():  # numpy's two-line "no data" warning: refused below
                warnings.filterwarnings("ignore", "loadtxt: input contained no data", UserWarning)
                ids = np.loadtxt(path, dtype=np.int64, ndmin=2, comments="#", encoding="utf-8-sig")
    except (OSError, ValueError, OverflowError) as exc:
        raise ValueError(f"cannot read node ids from {path}: {exc}") from exc
    if not np.issubdtype(ids.dtype, np.integer):
        raise ValueError(f"{path} must hold integer node ids, got {ids.dtype}")
    # a table's columns would be read as ids, flattened; an array's one row of ids is a list
    # of them, a text file's is not (one id a line)
    if ids.ndim > 1 and ids.size != (max(ids.shape) if path.suffix == ".npy" else len(ids)):
        raise ValueError(f"{path} holds rows of {ids.size // len(ids)} ids: node ids go one id a line")
    if ids.size == 0:
        raise ValueError(f"{path} holds no node id")
    big = ids[ids > np.iinfo(np.int64).max] if ids.dtype == np.uint64 else ids[:0]
    if big.size:  # checked before the cast, which wraps them round to negative ids ("got [-1]")
        raise ValueError(f"{path} holds node ids past any mesh's nodes (at most 2^63 - 1): {big.tolist()[:10]}")
    return ids.ravel().astype(np.int64)


def map_ids(ids: Any, key: str, loaded: LoadedMesh | None, origin: str) -> Array:
    """File node ids -> mesh ids, refusing ids out of range or of dropped nodes."""
    ids = np.asarray(ids, np.int64).ravel()
    if loaded is None:  # no record of loading: the ids are taken as mesh ids
        return ids
    n = loaded.n_source_nodes
    out = ids[(ids < 0) | (ids >= n)]
    if out.size:
        raise scene_error(origin, key, f"node ids must lie in 0..{n - 1}, got {out.tolist()[:10]}")
    mapped = loaded.source_to_mesh()[ids]
    if (mapped < 0).any():
        raise scene_error(origin, key, f"nodes {ids[mapped < 0].tolist()[:10]} belong to no tet (dropped on loading)")
    return mapped


def fixed_nodes(b: BoundarySpec, loaded: LoadedMesh, default_fixed: Array | None, origin: str) -> tuple[Array, str]:
    """[boundary]'s fixed nodes in the mesh's numbering (sorted), and the key that chose them.

    Refuses a selection that leaves the static problem singular: no node fixed, or all of them
    at one point or along one line (the body can still turn about them).
    """
    key = "[boundary]"
    if b.fixed_nodes is not None:
        key = "[boundary] fixed_nodes"
        fixed = map_ids(b.fixed_nodes, key, loaded, origin)
    elif b.fixed_nodes_file is not None:
        key = "[boundary] fixed_nodes_file"
        fixed = map_ids(read_ids(b.fixed_nodes_file, key, origin), key, loaded, origin)
    elif b.fixed_box is not None:
        key = "[boundary] fixed_box"
        lo, hi = np.asarray(b.fixed_box, np.float64)
        fixed = np.flatnonzero(((loaded.nodes >= lo) & (loaded.nodes <= hi)).all(axis=1))
        if fixed.size == 0:
            box = np.stack([loaded.nodes.min(0), loaded.nodes.max(0)]).round(6).tolist()
            raise scene_error(origin, "[boundary] fixed_box", f"selects no node (the mesh spans {box})")
    else:  # a generator's own clamp (a path scene is refused at validation without one)
        fixed = default_fixed
    if b.free_nodes:
        free = map_ids(b.free_nodes, "[boundary] free_nodes", loaded, origin)
        stray = np.setdiff1d(free, fixed)
        if stray.size:
            log.warning("%s: free_nodes %s were not fixed anyway", origin, stray.tolist()[:10])
        fixed = np.setdiff1d(fixed, free)
    fixed = np.unique(fixed)
    if fixed.size == 0:
        raise scene_error(
            origin,
            "[boundary]",
            "no node is fixed, so the static problem is singular (rigid motions are free): fix at least one node",
        )
    at = loaded.nodes[fixed] - loaded.nodes[fixed].mean(axis=0)
    spread = np.linalg.matrix_rank(at, tol=1e-6 * float(np.ptp(loaded.nodes, axis=0).max())) if fixed.size > 1 else 0
    if spread < 2:  # held at a point or along a line: it can still turn about it
        raise scene_error(
            origin,
            "[boundary]",
            f"the {fixed.size} fixed node(s) lie {'at one point' if spread == 0 else 'on one line'}, so the body "
            "can still turn about them and the static problem is singular: fix three or more nodes not in a line",
        )
    return fixed, key


def region_nodes(t: TrainingSpec, mesh: TetMesh, loaded: LoadedMesh | None, origin: str) -> Array:
    """[training]'s load region: free surface nodes where training loads may be centred (every
    one by default). Listed ids must be free surface nodes; box and sphere keep the free surface
    nodes inside. Shape: (r,) sorted mesh ids."""
    free_surface = mesh.free_surface_nodes
    if t.region is not None or t.region_file is not None:
        key = "[training] region" if t.region is not None else "[training] region_file"
        raw = t.region if t.region is not None else read_ids(t.region_file, key, origin)
        ids = _free_surface_ids(raw, key, mesh, loaded, origin)
        if ids.size == 0:
            raise scene_error(origin, key, "lists no node: the load region holds no free surface node")
        return _check_patch(t, ids, origin)
    if t.region_box is not None:
        key = "[training] region_box"
        lo, hi = np.asarray(t.region_box, np.float64)
        x = mesh.nodes[free_surface]
        ids = free_surface[((x >= lo) & (x <= hi)).all(axis=1)]
    elif t.region_sphere is not None:
        key = "[training] region_sphere"
        centre = np.asarray(t.region_sphere.centre, np.float64)
        dist = np.linalg.norm(mesh.nodes[free_surface] - centre, axis=1)
        ids = free_surface[dist <= t.region_sphere.radius]
    else:
        key, ids = "[training]", free_surface
    if ids.size == 0:
        raise scene_error(origin, key, "the load region holds no free surface node")
    return _check_patch(t, np.asarray(ids, np.int64), origin)


def keep_off_nodes(
    t: TrainingSpec, mesh: TetMesh, loaded: LoadedMesh | None, origin: str, region: Array | None = None
) -> Array:
    """[training] keep_off: the load region's nodes no training load may touch (none by default).
    Listed ids must be free surface nodes; those outside the region are dropped (no load reaches
    them anyway). What is left of the region must hold the smallest patch in one connected piece
    (loads spread along the surface between nodes left: surrogate/data.py). `region`: the load
    region where the caller has it (region_nodes' answer). Shape: (k,)."""
    if t.keep_off is None and t.keep_off_file is None:
        return np.zeros(0, np.int64)
    key = "[training] keep_off" if t.keep_off is not None else "[training] keep_off_file"
    raw = t.keep_off if t.keep_off is not None else read_ids(t.keep_off_file, key, origin)
    ids = _free_surface_ids(raw, key, mesh, loaded, origin)
    if region is None:
        region = region_nodes(t, mesh, loaded, origin)
    kept = np.intersect1d(ids, region)
    left = np.setdiff1d(region, kept)
    _, pieces = mesh.surface_pieces(left)
    largest = int(np.bincount(pieces).max()) if left.size else 0
    if largest < int(t.patch_nodes[0]):  # loads are spread along the surface between nodes left
        raise scene_error(
            origin,
            key,
            f"leaves {left.size} of the load region's {region.size} nodes, the largest connected piece of them "
            f"{largest} nodes, fewer than the smallest load patch ({int(t.patch_nodes[0])}): keep fewer nodes off "
            "or widen the region",
        )
    return kept


def _free_surface_ids(raw: Any, key: str, mesh: TetMesh, loaded: LoadedMesh | None, origin: str) -> Array:
    """A key's listed ids in mesh ids, sorted and unique, refused unless every one is a free surface node."""
    ids = np.unique(map_ids(raw, key, loaded, origin))
    bad = np.setdiff1d(ids, mesh.free_surface_nodes)
    if bad.size:
        raise scene_error(
            origin,
            key,
            f"{bad.size} nodes are not free surface nodes (interior or fixed): "
            f"{bad.tolist()[:10]}{' ...' if bad.size > 10 else ''}",
        )
    return ids


def _check_patch(t: TrainingSpec, region: Array, origin: str) -> Array:
    """Refuses a region smaller than the smallest load patch: every sampled load would cover
    fewer nodes than the scene says, and the served model's estimate would take the scene's
    patch as its tool's size (store.tool_patch)."""
    low = int(t.patch_nodes[0])
    if region.size < low:
        raise scene_error(
            origin,
            "[training] patch_nodes",
            f"a load spreads over at least {low} nodes, but the load region holds {region.size} free "
            f"surface nodes: lower patch_nodes or widen the region",
        )
    return region


def support_nodes(r: RegistrationSpec | None, loaded: LoadedMesh | None, origin: str) -> Array | None:
    """[registration] support nodes in mesh ids, or None when the scene names none. Shape: (k,)."""
    if r is None or (r.support is None and r.support_file is None):
        return None
    key = "[registration] support" if r.support is not None else "[registration] support_file"
    raw = r.support if r.support is not None else read_ids(r.support_file, key, origin)
    return np.unique(map_ids(raw, key, loaded, origin))


def matching_faces(r: RegistrationSpec | None, loaded: LoadedMesh | None, origin: str) -> Array | None:
    """[registration] matching triangles in mesh ids, or None when the scene names none.
    Shape: (f, 3)."""
    if r is None or r.matching_file is None:
        return None
    key = "[registration] matching_file"
    try:
        faces = np.load(r.matching_file, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise scene_error(origin, key, f"cannot read {r.matching_file}: {exc}") from exc
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise scene_error(origin, key, f"must hold an (f, 3) integer array, got {faces.dtype} {faces.shape}")
    ids = map_ids(faces.ravel(), key, loaded, origin)
    return ids.reshape(-1, 3)

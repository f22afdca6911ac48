"""Mesh files in: tetrahedral meshes through meshio, closed surfaces through trimesh + tetgen.

Whatever the format, what comes out has been through :meth:`TetMesh.build`, so a bad file is
refused here with a :class:`MeshError` naming it, not deep inside a solve.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import logging
import os
import subprocess
import sys
import tempfile
from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType

import numpy as np

from .mesh import MeshError, TetMesh
from .optional import need

log = logging.getLogger(__name__)

Array = np.ndarray

#: Suffixes read as closed triangle surfaces and tetrahedralised; anything else goes to meshio.
SURFACE_SUFFIXES = frozenset({".stl", ".obj", ".ply", ".off"})

#: meshio's cell kinds read as tets (a quadratic tet keeps its four corners)
TET_KINDS = ("tetra", "tetra10")
#: legacy gmsh v1 element types read as tets, as TET_KINDS (a quadratic tet, 11, lists its corners first)
GMSH1_TETS = ("4", "11")
#: legacy gmsh v1 element types that fill volume, by meshio's names: dropped, they cut the body
GMSH1_VOLUME = {
    "5": "hexahedron",
    "6": "wedge",
    "7": "pyramid",
    "12": "hexahedron27",
    "13": "wedge18",
    "14": "pyramid14",
    "17": "hexahedron20",
    "18": "wedge15",
    "19": "pyramid13",
}

#: TetGen options, as switches ``-pq1.5/18Y -O10/7 -o/165 -Q``: fill a piecewise-linear complex
#: (p) with quality tets (radius-edge ratio <= 1.5, target dihedral >= 18 deg: q), keep the
#: surface triangulation as given so its vertices come out first and unchanged (Y), then the
#: strongest optimisation (flips, smoothing, insertion; 20 passes, aiming at dihedral <= 165 deg)
#: to remove the slivers Delaunay refinement leaves. Passed as keywords: the switch-string path
#: of the tetgen package writes to stdout. TetGen is deterministic for a given input.
TETGEN_OPTIONS: Mapping[str, object] = MappingProxyType(
    dict(
        plc=True,
        quality=True,
        minratio=1.5,
        mindihedral=18.0,
        nobisect=True,
        opt_max_flip_level=10,
        opt_scheme=7,
        opt_iterations=20,
        optmaxdihedral=165.0,
        quiet=True,
    )
)

#: A tet whose smallest dihedral angle is below this many degrees counts as a sliver.
SLIVER_DEG = 5.0

#: the span (bounding-box diagonal, m) a scaled mesh may have: a micron to 1,000 km, beyond any
#: organ in any unit (past it a wrong scale gave inf coordinates or zero volumes, blamed on the file)
SCALED_SPAN = (1e-6, 1e6)


class ScaleError(MeshError):
    """A scale that puts the mesh outside SCALED_SPAN: the scale's fault, not the file's."""


def scaled(points: Array, scale: float, source: object, cells: Array) -> Array:
    """`points` x `scale`, refused (ScaleError) where the scaled span of the points `cells` use
    is outside SCALED_SPAN (a stray node no cell uses is dropped later: it judges no scale)."""
    used = np.unique(np.asarray(cells, np.int64))
    used = used[(used >= 0) & (used < len(points))]  # bad ids are the mesh check's to name
    raw = float(np.linalg.norm(np.ptp(points[used], axis=0))) if used.size else 0.0
    span = raw * scale  # a Python float: inf past the largest, no warning
    if np.isfinite(raw) and raw > 0 and not SCALED_SPAN[0] <= span <= SCALED_SPAN[1]:
        raise ScaleError(
            f"scale {scale:g} makes {source} span {span:.3g} m corner to corner ({raw:.3g} x {scale:g}), outside "
            f"{SCALED_SPAN[0]:g}..{SCALED_SPAN[1]:g} m: the scale turns the file's unit into metres (millimetres: "
            "0.001)"
        )
    return points * scale


_EDGE_PAIRS = np.array([(i, j) for i in range(4) for j in range(i + 1, 4)])


@dataclasses.dataclass(frozen=True)
class MeshQuality:
    """Shape statistics of a tet mesh: angles in degrees, volume in the mesh's (scaled) units."""

    min_dihedral: float
    max_dihedral: float
    n_slivers: int  # tets whose smallest dihedral angle is < SLIVER_DEG
    volume: float


@dataclasses.dataclass(frozen=True, eq=False)
class LoadedMesh:
    """A mesh read from a file (or generated), validated and repaired.

    Shape: nodes (n, 3) float64 after scaling, tets (t, 4) int64 positively oriented, kept (n,)
    or None. `kept[i]` is the file's id of node i when unused nodes were dropped (None when every
    node was kept); `n_source_nodes` is the file's node count, the range of ids a scene may use.
    A surface's file ids are its vertices' (`file_ids`); tetgen numbers its nodes otherwise.
    """

    nodes: Array
    tets: Array
    source: Path | None
    tetrahedralised: bool
    kept: Array | None
    n_source_nodes: int
    quality: MeshQuality
    file_ids: Array | None = None  # a surface's: each file vertex's mesh id (-1: in no face)

    @property
    def renumbered(self) -> bool:
        """Whether the mesh's nodes are not the file's one for one: unused ones dropped, or a
        surface tetrahedralised (nodes added inside); the model summary says so (API.md)."""
        return self.kept is not None or self.tetrahedralised

    def source_to_mesh(self) -> Array:
        """Map from the file's node ids to mesh ids (-1 for dropped nodes). Shape: (n_source,)."""
        if self.file_ids is not None:
            return self.file_ids
        if self.kept is None:
            return np.arange(self.n_source_nodes, dtype=np.int64)
        new_id = np.full(self.n_source_nodes, -1, np.int64)
        new_id[self.kept] = np.arange(self.kept.size)
        return new_id

    def mesh_to_source(self) -> Array:
        """Map from mesh ids to the file's node ids (-1 for a node the file has none for: one a
        surface's tetrahedralisation added). Shape: (n,)."""
        forward = self.source_to_mesh()
        back = np.full(len(self.nodes), -1, np.int64)
        has = forward >= 0
        back[forward[has]] = np.flatnonzero(has)
        return back

    def to_mesh(self, fixed: Array | None = None) -> TetMesh:
        """The TetMesh with these Dirichlet nodes (mesh ids; the arrays are already validated)."""
        return TetMesh(self.nodes, self.tets, np.zeros(0, np.int64) if fixed is None else fixed)


def dihedral_angles(nodes: Array, tets: Array) -> Array:
    """The six interior dihedral angles of each tet, in degrees.

    Shape: nodes (n, 3), tets (t, 4) -> (t, 6).
    The angle at the edge opposite nodes k, l is pi minus the angle between the gradients of
    their shape functions (inward normals of the faces opposite k and l).
    """
    x = nodes[tets]
    D = np.transpose(x[:, 1:] - x[:, :1], (0, 2, 1))
    g = np.empty((len(tets), 4, 3))
    g[:, 1:] = np.linalg.inv(D)
    g[:, 0] = -g[:, 1:].sum(axis=1)
    g /= np.linalg.norm(g, axis=2, keepdims=True)
    cos = -(g[:, _EDGE_PAIRS[:, 0]] * g[:, _EDGE_PAIRS[:, 1]]).sum(axis=2)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def mesh_quality(nodes: Array, tets: Array) -> MeshQuality:
    """Dihedral-angle extremes, sliver count and volume of a (positively oriented) mesh."""
    ang = dihedral_angles(nodes, tets)
    x = nodes[tets]
    vol = np.linalg.det(x[:, 1:] - x[:, :1]).sum() / 6.0
    return MeshQuality(
        min_dihedral=float(ang.min()),
        max_dihedral=float(ang.max()),
        n_slivers=int((ang.min(axis=1) < SLIVER_DEG).sum()),
        volume=float(vol),
    )


def _file_vertex_ids(points: Array, merged: Array) -> Array:
    """Each file vertex's id among the merged vertices: the one at its place (-1 where none is,
    a vertex no face uses). Shape: (v_file,)."""
    from scipy.spatial import cKDTree

    size = float(np.ptp(merged, axis=0).max()) or 1.0
    dist, near = cKDTree(merged).query(points)
    return np.where(dist <= 1e-6 * size, near, -1).astype(np.int64)


def _obj_points(path: Path) -> Array:
    """An .obj file's vertex list as written (trimesh's reader drops and reorders vertices)."""
    rows = [line.split()[1:4] for line in path.read_text(errors="replace").splitlines() if line.startswith("v ")]
    try:
        return np.array(rows, np.float64).reshape(-1, 3)
    except ValueError as exc:
        raise MeshError(f"{path}: a vertex line is not three numbers ({exc})") from None


def tetrahedralise(
    vertices: Array,
    faces: Array,
    *,
    max_volume: float | None = None,
) -> tuple[Array, Array]:
    """Fill a closed triangle surface with quality tets (tetgen, :data:`TETGEN_OPTIONS`).

    Shape: vertices (v, 3), faces (f, 3) -> nodes (n, 3) whose first v rows are `vertices`,
    tets (t, 4) int64.
    `max_volume` adds TetGen's -a bound (same units as the vertices, cubed) for a finer interior.
    """
    need("tetgen", "filling a closed surface with tets")  # only surfaces need it
    options = dict(TETGEN_OPTIONS)
    if max_volume is not None:
        options.update(fixedvolume=True, maxvolume=float(max_volume))
    # in a child process: on a self-intersecting surface tetgen reports the error and then
    # corrupts its process's heap (an abort in whatever comes next), and it writes its
    # _skipped files into the working directory
    with tempfile.TemporaryDirectory(prefix="elastreg-tetgen-") as scratch:
        np.savez(
            Path(scratch) / "surface.npz",
            vertices=np.asarray(vertices, np.float64),
            faces=np.asarray(faces, np.int32),
            options=json.dumps(options),
        )
        path = os.pathsep.join(filter(None, (_PACKAGE_ROOT, os.environ.get("PYTHONPATH"))))
        child = "import sys; from service.meshfile import _tetgen_child; _tetgen_child(sys.argv[1])"
        run = subprocess.run(
            [sys.executable, "-c", child, scratch],
            cwd=scratch,
            capture_output=True,
            text=True,
            env={**os.environ, "PYTHONPATH": path},
        )
        if run.returncode != 0:
            lines = run.stderr.strip().splitlines() or ["no message"]
            said = next((line for line in reversed(lines) if "Error" in line), lines[-1])
            raise MeshError(f"tetgen could not fill the surface: is it self-intersecting? ({said})")
        with np.load(Path(scratch) / "tets.npz") as z:
            return z["nodes"].astype(np.float64), z["tets"].astype(np.int64)


#: where `service` imports from, for the child process
_PACKAGE_ROOT = str(Path(__file__).resolve().parents[1])


def _tetgen_child(scratch: str) -> None:
    """tetgen on the surface saved in `scratch`, its tets saved beside it (a child process)."""
    import tetgen

    with np.load(Path(scratch) / "surface.npz") as z:
        vertices, faces, options = z["vertices"], z["faces"], json.loads(str(z["options"]))
    nodes, tets, *_ = tetgen.TetGen(vertices, faces).tetrahedralize(**options)
    np.savez(Path(scratch) / "tets.npz", nodes=nodes, tets=tets)


def _read_surface(path: Path) -> tuple[Array, Array, Array]:
    """A closed triangle surface from an .stl/.obj/.ply/.off file, merged and outward oriented.

    Returns its vertices (v, 3), faces (f, 3) and each file vertex's id among them (-1 where no
    face uses it): a scene's node ids are the file's, and an .stl repeats a vertex per face.
    """
    import trimesh

    try:
        raw = trimesh.load_mesh(path, process=False)
        surf = trimesh.load_mesh(path, process=True)  # equal (to 1e-8) vertices merged, unused dropped
    except Exception as exc:  # trimesh's loaders raise many types on a corrupt file
        raise MeshError(f"{path}: trimesh could not read it ({type(exc).__name__}: {exc})") from exc
    if not isinstance(surf, trimesh.Trimesh) or not isinstance(raw, trimesh.Trimesh) or len(surf.faces) == 0:
        raise MeshError(f"{path}: no triangles in this surface file")
    points = _obj_points(path) if path.suffix.lower() == ".obj" else np.asarray(raw.vertices)
    vertex_id = _file_vertex_ids(points, np.asarray(surf.vertices))
    if not surf.is_watertight:
        edges = np.sort(surf.edges, axis=1)
        _, counts = np.unique(edges, axis=0, return_counts=True)
        raise MeshError(
            f"{path}: the surface is not watertight ({int((counts == 1).sum())} open edges, "
            f"{int((counts > 2).sum())} non-manifold edges); only a closed surface encloses a "
            "volume to fill with tets: close it, or give a tetrahedral mesh"
        )
    if not surf.is_winding_consistent:
        raise MeshError(f"{path}: the surface's triangles are not consistently oriented")
    if surf.volume < 0:
        surf.invert()
    return np.asarray(surf.vertices, np.float64), np.asarray(surf.faces, np.int64), vertex_id


def _is_gmsh1(path: Path) -> bool:
    if path.suffix.lower() != ".msh":
        return False
    with open(path, "rb") as f:
        return f.read(64).lstrip().startswith(b"$NOD")


def _read_gmsh1(path: Path) -> tuple[Array, Array]:
    """Nodes and tets of a legacy gmsh v1 file ($NOD/$ELM, e.g. SOFA's meshes), which meshio
    cannot read. Element rows are: id, type, reg-phys, reg-elem, n, node ids; type 4 is a tet,
    type 11 a quadratic one, which keeps its four corners (its mid-edge nodes are dropped later
    as unused, as meshio's tetra10 are).
    """
    lines = path.read_text().split("\n")
    try:
        i = next(k for k, line in enumerate(lines) if line.strip() == "$NOD")
        n = int(lines[i + 1])
        node_text = np.array([line.split() for line in lines[i + 2 : i + 2 + n]])
        labels, coords = node_text[:, 0].astype(np.int64), node_text[:, 1:4].astype(np.float64)
        j = next(k for k, line in enumerate(lines) if line.strip() == "$ELM")
        m = int(lines[j + 1])
        rows = [line.split() for line in lines[j + 2 : j + 2 + m]]
        tets = np.array([r[5:9] for r in rows if r[1] in GMSH1_TETS], np.int64)
    except (ValueError, IndexError, StopIteration, OverflowError) as exc:
        raise MeshError(f"{path}: not a readable gmsh v1 file ({exc})") from exc
    if len(tets) == 0:
        raise MeshError(f"{path}: no tetrahedra in this file")
    negative = np.unique(labels[labels < 0])
    if negative.size:  # gmsh numbers nodes from 1: a negative label is a damaged file
        raise MeshError(f"{path}: node labels must be >= 0 (gmsh numbers them from 1), got {_some(negative)}")
    # gmsh labels are arbitrary: mapped to rows by search, never by an array as long as the largest
    order = np.argsort(labels, kind="stable")
    rows_of = order[np.minimum(np.searchsorted(labels, tets, sorter=order), len(labels) - 1)]
    if not (labels[rows_of] == tets).all():
        raise MeshError(f"{path}: elements refer to undefined nodes")
    log.info("%s: legacy gmsh v1 file, %d tets (other elements ignored)", path.name, len(tets))
    _warn_dropped_volume(path, dict(Counter(GMSH1_VOLUME[r[1]] for r in rows if r[1] in GMSH1_VOLUME)))
    return coords, rows_of


def _some(values: Array, shown: int = 5) -> str:
    """At most `shown` values of an array for a message, with how many more there are."""
    said = ", ".join(str(v) for v in values[:shown])
    return said + (f" and {values.size - shown} more" if values.size > shown else "")


def _warn_dropped_volume(path: Path, counts: dict[str, int]) -> None:
    """A warning naming the volume cells other than tets that loading drops (`counts`: kind ->
    cells): the mesh then lacks their part of the body, unlike a file's boundary triangles."""
    if counts:
        said = ", ".join(f"{n} {kind}" for kind, n in sorted(counts.items()))
        log.warning(
            "%s: dropped %s cells (only tets are used): the mesh lacks their volume; split them into tets to keep it",
            path.name,
            said,
        )


def _read_tets(path: Path) -> tuple[Array, Array]:
    """Nodes and 4-node tets of any volume mesh meshio reads; other cells are ignored.

    Why ignore: gmsh files carry boundary triangles (and lines, points) beside the tets.
    Quadratic tets (tetra10) keep their four corners; the mid-edge nodes are dropped later as
    unused.
    """
    import meshio

    if _is_gmsh1(path):
        return _read_gmsh1(path)
    chatter = io.StringIO()  # meshio's readers print notes (through rich): log them instead
    try:
        with contextlib.redirect_stdout(chatter), contextlib.redirect_stderr(chatter):
            m = meshio.read(path)
    # meshio raises many types (ReadError, KeyError, ValueError ...), and exits on a format it
    # cannot guess: neither may take the service down
    except (Exception, SystemExit) as exc:
        said = " ".join(chatter.getvalue().split())
        raise MeshError(f"{path}: meshio could not read it ({type(exc).__name__}: {said or exc})") from exc
    if chatter.getvalue().strip():
        log.debug("%s: meshio says: %s", path.name, " ".join(chatter.getvalue().split()))
    blocks = [c.data[:, :4] for c in m.cells if c.type in TET_KINDS]
    if not blocks:
        kinds = sorted({c.type for c in m.cells}) or ["none"]
        raise MeshError(
            f"{path}: no tetrahedra in this file (cells: {', '.join(kinds)}); "
            "give a tetrahedral volume mesh, or a closed surface as .stl/.obj/.ply to tetrahedralise"
        )
    ignored = sum(len(c.data) for c in m.cells if c.type not in TET_KINDS)
    if ignored:
        log.info("%s: ignored %d non-tet cells (boundary triangles, lines, ...)", path.name, ignored)
    volume: dict[str, int] = {}
    for c in m.cells:  # cell blocks, a few per file
        if c.type not in TET_KINDS and c.dim == 3:  # meshio: the kind's topological dimension
            volume[c.type] = volume.get(c.type, 0) + len(c.data)
    _warn_dropped_volume(path, volume)
    return np.asarray(m.points, np.float64)[:, :3], np.concatenate(blocks).astype(np.int64)


def load_mesh(path: str | Path, scale: float = 1.0, *, max_volume: float | None = None) -> LoadedMesh:
    """Read a tetrahedral mesh or tetrahedralise a closed surface, scale it, and validate it.

    Shape: result.nodes (n, 3) = file coordinates x `scale`.
    `max_volume` (after scaling) bounds tet volume when a surface is tetrahedralised.
    Raises MeshError with the file's name for anything unusable.
    """
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{path}: no such mesh file")
    if not scale > 0:
        raise MeshError(f"{path}: scale must be > 0, got {scale}")
    surface = path.suffix.lower() in SURFACE_SUFFIXES
    file_ids = None
    if surface:
        vertices, faces, file_ids = _read_surface(path)
        vertices = scaled(vertices, scale, path.name, faces)
        try:
            nodes, tets = tetrahedralise(vertices, faces, max_volume=max_volume)
        except MeshError as exc:
            raise MeshError(f"{path}: {exc}") from exc
        log.info(
            "%s: tetrahedralised %d surface vertices into %d nodes, %d tets",
            path.name,
            len(vertices),
            len(nodes),
            len(tets),
        )
    else:
        nodes, tets = _read_tets(path)
        nodes = scaled(nodes, scale, path.name, tets)
    try:
        mesh, kept = TetMesh.build(nodes, tets)
    except MeshError as exc:
        raise MeshError(f"{path}: {exc}") from exc
    quality = mesh_quality(mesh.nodes, mesh.tets)
    if quality.n_slivers:  # a warning only when they are more than a stray few
        level = logging.WARNING if quality.n_slivers > 0.01 * mesh.n_tets else logging.INFO
        log.log(level, "%s: %d sliver tets (min dihedral %.1f deg)", path.name, quality.n_slivers, quality.min_dihedral)
    log.info("%s: %d nodes, %d tets, min dihedral %.1f deg", path.name, mesh.n_nodes, mesh.n_tets, quality.min_dihedral)
    if file_ids is not None:  # a surface: its file's vertices, through tetgen's and the build's ids
        node_id = np.arange(len(nodes)) if kept is None else np.full(len(nodes), -1, np.int64)
        if kept is not None:
            node_id[kept] = np.arange(kept.size)
        file_ids = np.where(file_ids >= 0, node_id[np.maximum(file_ids, 0)], -1)
    return LoadedMesh(
        nodes=mesh.nodes,
        tets=mesh.tets,
        source=path,
        tetrahedralised=surface,
        kept=kept,
        n_source_nodes=len(nodes) if file_ids is None else len(file_ids),
        quality=quality,
        file_ids=file_ids,
    )

"""Scenes: the TOML file of SCENES.md, validated into pydantic models, and the mesh it names.

Every key is checked at load time and every error names its key, e.g.
``scene.toml: [material] nu: must be < 0.5, got 0.6``, so a bad scene fails before hours of
training, not during them. All errors are one type, :class:`SceneError` (a ``ValueError``).

Keys beyond SCENES.md (all optional):

- ``[mesh] generator = "beam" | "phantom"``: a procedural mesh of :mod:`service.phantoms`
  instead of ``path`` (exactly one of the two); ``[boundary]`` may then be left out, and the
  generator's own clamp is used.
- ``[boundary] free_nodes = [...]``: node ids released from the fixed selection.
- ``[training] region_sphere = {centre = [x, y, z], radius = r}``: the free surface nodes within
  r of the centre (coordinates after scaling), beside ``region``/``region_file``/``region_box``.
- ``[training] seed`` (0), ``load_steps`` (5: converged steps kept along one load path),
  ``multi_patch`` (0.2: fraction of samples loaded on two patches), ``normal_fraction`` (0.5: how
  much of a load is along the surface normal rather than tangential, on average),
  ``pull_fraction`` (2/3: how often the normal part pulls outwards, as a grasper does),
  ``twist_fraction`` (0: how often a patch carries a torque instead of a single direction),
  ``members`` (1: the surrogate's ensemble size, see :mod:`service.surrogate.network`;
  ``elastreg train --members`` overrides it).
- ``[registration]``: read by the benchmark and the trainer: ``support`` or ``support_file``
  (node ids where registration may put forces), ``matching_file`` (a .npy (f, 3) array of the
  boundary triangles point clouds lie on).

An id file (``*_file`` but ``matching_file``) is a .npy array or text with one id a line ('#'
comments): two or more ids a line, or none, are refused. A UTF-8 BOM before a scene or an id
file is skipped. Paths (``path`` and every ``*_file`` key) are relative to the TOML file. Node ids in a scene are
the file's ids; when loading drops unused nodes they are mapped onto the mesh's numbering.
"""

from __future__ import annotations

import logging
import re
import tomllib
import warnings
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from .mesh import MeshError, TetMesh
from .meshfile import LoadedMesh, load_mesh, mesh_quality

log = logging.getLogger(__name__)

Array = np.ndarray

#: A model id, the one rule for every place one is named: a scene's `name`, `elastreg train
#: --name`, a store entry's folder and manifest, the {model} segment of the API's URLs. A letter
#: or digit first: never "." or "..", nor a hidden folder (the store's temporaries, .ID-*, and
#: the entries it sets aside, ..ID-*); then only URL-unreserved characters, so a URL needs no
#: escaping; 64 at most.
MODEL_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
MODEL_ID_RULE = "must start with a letter or digit and hold only letters, digits, '_', '.' and '-' (64 at most)"


def check_model_id(model_id: str) -> str:
    """`model_id` if it is one (MODEL_ID), else a ValueError that says the rule."""
    if not isinstance(model_id, str) or not MODEL_ID.fullmatch(model_id):
        raise ValueError(f"model id {model_id!r:.80} {MODEL_ID_RULE}")
    return model_id


#: Scenes shipped in the package (service/scenes/NAME.toml).
BUILTIN_SCENES = ("beam", "phantom")
GENERATORS = ("beam", "phantom")
TABLES = ("mesh", "material", "boundary", "training", "registration")


class SceneError(ValueError):
    """A scene that cannot be used; the message names the file and the key."""


# -- field types ------------------------------------------------------------------------------


def _resolve_path(value: Path, info: ValidationInfo) -> Path:
    """Make a path absolute against the TOML file's folder, and check that the file is there."""
    base = (info.context or {}).get("base")
    path = value.expanduser()
    if not path.is_absolute() and base is not None:
        path = Path(base) / path
    path = path.resolve()
    if not path.is_file():
        raise ValueError(f"file not found: {path}")
    return path


ScenePath = Annotated[Path, AfterValidator(_resolve_path)]
NodeId = Annotated[int, Field(strict=True, ge=0)]
Finite = Annotated[float, Field(strict=True, allow_inf_nan=False)]  # strict: no bool, no string
Vec3 = tuple[Finite, Finite, Finite]
Fraction = Annotated[float, Field(strict=True, ge=0.0, le=1.0)]
Count = Annotated[int, Field(strict=True, ge=1)]


def _check_box(box: tuple[Vec3, Vec3] | None) -> tuple[Vec3, Vec3] | None:
    if box is not None and any(lo > hi for lo, hi in zip(*box, strict=True)):
        raise ValueError(
            f"must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with min <= max, got {[list(corner) for corner in box]}"
        )
    return box


Box = Annotated[tuple[Vec3, Vec3], AfterValidator(_check_box)]


def _given(model: BaseModel, keys: tuple[str, ...]) -> list[str]:
    return [k for k in keys if getattr(model, k) is not None]


class _Table(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


# -- tables -----------------------------------------------------------------------------------


class MeshSpec(_Table):
    """[mesh]: a file (tetrahedral, or a closed surface to tetrahedralise) or a generator."""

    path: ScenePath | None = None
    generator: Literal["beam", "phantom"] | None = None
    scale: Annotated[float, Field(strict=True, gt=0.0, allow_inf_nan=False)] = 1.0

    @model_validator(mode="after")
    def _one_source(self) -> MeshSpec:
        if (self.path is None) == (self.generator is None):
            raise ValueError("give exactly one of path, generator")
        return self


class MaterialSpec(_Table):
    """[material]: the Neo-Hookean law of SCENES.md (the only one)."""

    law: Literal["neo-hookean"] = "neo-hookean"
    E: Annotated[float, Field(strict=True, gt=0.0, allow_inf_nan=False)]
    nu: Annotated[float, Field(strict=True, ge=0.0, lt=0.5)]


#: the span (bounding-box diagonal, m) outside which a mesh is probably in the wrong unit: a
#: finger's width to a torso's
ORGAN_SIZE = (0.01, 2.0)

FIXED_KEYS = ("fixed_nodes", "fixed_nodes_file", "fixed_box")


class BoundarySpec(_Table):
    """[boundary]: the Dirichlet nodes, by id list, id file or box, minus free_nodes."""

    fixed_nodes: list[NodeId] | None = None
    fixed_nodes_file: ScenePath | None = None
    fixed_box: Box | None = None
    free_nodes: list[NodeId] = []

    @model_validator(mode="after")
    def _at_most_one(self) -> BoundarySpec:
        given = _given(self, FIXED_KEYS)
        if len(given) > 1:
            raise ValueError(f"give exactly one of {', '.join(FIXED_KEYS)} (got {', '.join(given)})")
        return self


class Sphere(_Table):
    centre: Vec3
    radius: Annotated[float, Field(strict=True, gt=0.0, allow_inf_nan=False)]


REGION_KEYS = ("region", "region_file", "region_box", "region_sphere")


class TrainingSpec(_Table):
    """[training]: how many samples, how strong, how spread, and where loads may act."""

    samples: Count
    max_force: Annotated[float, Field(strict=True, gt=0.0, allow_inf_nan=False)]
    patch_nodes: tuple[Count, Count]
    region: list[NodeId] | None = None
    region_file: ScenePath | None = None
    region_box: Box | None = None
    region_sphere: Sphere | None = None
    seed: Annotated[int, Field(strict=True, ge=0)] = 0
    load_steps: Count = 5
    multi_patch: Fraction = 0.2
    normal_fraction: Fraction = 0.5
    pull_fraction: Fraction = 2.0 / 3.0
    twist_fraction: Fraction = 0.0
    members: Count = 1

    @field_validator("patch_nodes")
    @classmethod
    def _ordered(cls, v: tuple[int, int]) -> tuple[int, int]:
        if v[0] > v[1]:
            raise ValueError(f"must be [lo, hi] with lo <= hi, got {list(v)}")
        return v

    @model_validator(mode="after")
    def _at_most_one(self) -> TrainingSpec:
        given = _given(self, REGION_KEYS)
        if len(given) > 1:
            raise ValueError(f"give at most one of {', '.join(REGION_KEYS)} (got {', '.join(given)})")
        return self


class RegistrationSpec(BaseModel):
    """[registration]: optional inputs of the benchmark; a misspelt key is refused, as in every
    other table (`suport` kept quietly would leave the default support in its place)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    support: list[NodeId] | None = None
    support_file: ScenePath | None = None
    matching_file: ScenePath | None = None

    @model_validator(mode="after")
    def _at_most_one(self) -> RegistrationSpec:
        if self.support is not None and self.support_file is not None:
            raise ValueError("give at most one of support, support_file")
        return self


# -- the scene --------------------------------------------------------------------------------


class Scene(_Table):
    """One organ's scene: mesh, material, boundary conditions, and the loads to learn."""

    name: Annotated[str, Field(pattern=MODEL_ID.pattern)]  # the model id in the store and the API
    mesh: MeshSpec
    material: MaterialSpec
    boundary: BoundarySpec = BoundarySpec()
    training: TrainingSpec
    registration: RegistrationSpec | None = None

    _origin: str = PrivateAttr("<scene>")
    _loaded: dict = PrivateAttr(default_factory=dict)  # mesh.hash -> LoadedMesh, from build_mesh

    @model_validator(mode="after")
    def _boundary_needed(self) -> Scene:
        if self.mesh.path is not None and not _given(self.boundary, FIXED_KEYS):
            raise ValueError(
                "[boundary]: give exactly one of fixed_nodes, fixed_nodes_file, fixed_box "
                "(a mesh file has no default clamp)"
            )
        return self

    @property
    def origin(self) -> str:
        """Where the scene came from (its file, or builtin:NAME), for messages."""
        return self._origin

    def _error(self, key: str, message: str) -> SceneError:
        return SceneError(f"{self._origin}: {key}: {message}")

    # -- mesh ---------------------------------------------------------------------------------

    def load(self) -> LoadedMesh:
        """The scene's mesh, loaded or generated and scaled, before boundary conditions."""
        return self._load()[0]

    def _load(self) -> tuple[LoadedMesh, Array | None]:
        """The loaded mesh, and a generator's default clamp (None for a file)."""
        scale = self.mesh.scale
        if self.mesh.generator is not None:
            from . import phantoms

            gen = getattr(phantoms, self.mesh.generator)()
            nodes = gen.nodes * scale
            loaded = LoadedMesh(
                nodes=nodes,
                tets=gen.tets,
                source=None,
                tetrahedralised=self.mesh.generator == "phantom",
                kept=None,
                n_source_nodes=len(nodes),
                quality=mesh_quality(nodes, gen.tets),
            )
            return loaded, np.asarray(gen.fixed, np.int64)
        try:
            return load_mesh(self.mesh.path, scale), None
        except MeshError as exc:
            raise self._error("[mesh] path", str(exc)) from exc

    def build_mesh(self) -> tuple[TetMesh, LoadedMesh]:
        """The mesh with its fixed nodes resolved, and what loading it found.

        Shape: mesh.fixed (f,) in the mesh's numbering (mapped from the file's ids).
        Refuses a scene that fixes no node: the static problem would be singular.
        """
        loaded, default_fixed = self._load()
        b = self.boundary
        key = "[boundary]"
        if b.fixed_nodes is not None:
            key = "[boundary] fixed_nodes"
            fixed = self._map_ids(b.fixed_nodes, key, loaded)
        elif b.fixed_nodes_file is not None:
            key = "[boundary] fixed_nodes_file"
            fixed = self._map_ids(self._read_ids(b.fixed_nodes_file, key), key, loaded)
        elif b.fixed_box is not None:
            key = "[boundary] fixed_box"
            lo, hi = np.asarray(b.fixed_box, np.float64)
            fixed = np.flatnonzero(((loaded.nodes >= lo) & (loaded.nodes <= hi)).all(axis=1))
            if fixed.size == 0:
                box = np.stack([loaded.nodes.min(0), loaded.nodes.max(0)]).round(6).tolist()
                raise self._error("[boundary] fixed_box", f"selects no node (the mesh spans {box})")
        else:  # a generator's own clamp (a path scene is refused at validation without one)
            fixed = default_fixed
        if b.free_nodes:
            free = self._map_ids(b.free_nodes, "[boundary] free_nodes", loaded)
            stray = np.setdiff1d(free, fixed)
            if stray.size:
                log.warning("%s: free_nodes %s were not fixed anyway", self._origin, stray.tolist()[:10])
            fixed = np.setdiff1d(fixed, free)
        fixed = np.unique(fixed)
        if fixed.size == 0:
            raise self._error(
                "[boundary]",
                "no node is fixed, so the static problem is singular (rigid motions are free): fix at least one node",
            )
        at = loaded.nodes[fixed] - loaded.nodes[fixed].mean(axis=0)
        spread = (
            np.linalg.matrix_rank(at, tol=1e-6 * float(np.ptp(loaded.nodes, axis=0).max())) if fixed.size > 1 else 0
        )
        if spread < 2:  # held at a point or along a line: it can still turn about it
            raise self._error(
                "[boundary]",
                f"the {fixed.size} fixed node(s) lie {'at one point' if spread == 0 else 'on one line'}, so the body "
                "can still turn about them and the static problem is singular: fix three or more nodes not in a line",
            )
        mesh = loaded.to_mesh(fixed)
        if mesh.free_surface_nodes.size == 0:  # nothing a tool could push: say so here, not as an empty load region
            what = "every node" if fixed.size == mesh.n_nodes else "every surface node"
            raise self._error(key, f"fixes {what} ({fixed.size} of {mesh.n_nodes} nodes): nothing is left free to load")
        self._loaded[mesh.hash] = loaded
        log.info("%s: %d nodes, %d tets, %d fixed", self._origin, mesh.n_nodes, mesh.n_tets, mesh.fixed.size)
        size = float(np.linalg.norm(np.ptp(mesh.nodes, axis=0)))
        if not ORGAN_SIZE[0] <= size <= ORGAN_SIZE[1]:  # SCENES.md: metres; a file in mm needs scale 0.001
            log.warning(
                "%s: the mesh spans %.3g m corner to corner, not an organ's %g-%g m: is [mesh] scale right "
                "(a mesh in millimetres needs scale = 0.001)?",
                self._origin,
                size,
                *ORGAN_SIZE,
            )
        return mesh, loaded

    # -- node sets ----------------------------------------------------------------------------

    def region_nodes(self, mesh: TetMesh, loaded: LoadedMesh | None = None) -> Array:
        """Free surface nodes where training loads may be centred (every one by default).

        Shape: (r,) sorted mesh ids.
        `loaded` maps file ids to mesh ids; by default the one `build_mesh` made this mesh from.
        Listed ids must be free surface nodes; box and sphere keep the free surface nodes inside.
        """
        t = self.training
        free_surface = mesh.free_surface_nodes
        if t.region is not None or t.region_file is not None:
            key = "[training] region" if t.region is not None else "[training] region_file"
            raw = t.region if t.region is not None else self._read_ids(t.region_file, key)
            ids = np.unique(self._map_ids(raw, key, self._loaded_for(mesh, loaded)))
            bad = np.setdiff1d(ids, free_surface)
            if bad.size:
                raise self._error(
                    key,
                    f"{bad.size} nodes are not free surface nodes (interior or fixed): "
                    f"{bad.tolist()[:10]}{' ...' if bad.size > 10 else ''}",
                )
            if ids.size == 0:
                raise self._error(key, "lists no node: the load region holds no free surface node")
            return self._check_patch(ids)
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
            raise self._error(key, "the load region holds no free surface node")
        return self._check_patch(np.asarray(ids, np.int64))

    def _check_patch(self, region: Array) -> Array:
        """Refuses a region smaller than the smallest load patch: every sampled load would cover
        fewer nodes than the scene says, and the served model's estimate would take the scene's
        patch as its tool's size (store.tool_patch)."""
        low = int(self.training.patch_nodes[0])
        if region.size < low:
            raise self._error(
                "[training] patch_nodes",
                f"a load spreads over at least {low} nodes, but the load region holds {region.size} free "
                f"surface nodes: lower patch_nodes or widen the region",
            )
        return region

    def support_nodes(self, mesh: TetMesh, loaded: LoadedMesh | None = None) -> Array | None:
        """[registration] support nodes in mesh ids, or None when the scene names none.

        Shape: (k,).
        """
        r = self.registration
        if r is None or (r.support is None and r.support_file is None):
            return None
        key = "[registration] support" if r.support is not None else "[registration] support_file"
        raw = r.support if r.support is not None else self._read_ids(r.support_file, key)
        return np.unique(self._map_ids(raw, key, self._loaded_for(mesh, loaded)))

    def matching_faces(self, mesh: TetMesh, loaded: LoadedMesh | None = None) -> Array | None:
        """[registration] matching triangles in mesh ids, or None when the scene names none.

        Shape: (f, 3).
        """
        r = self.registration
        if r is None or r.matching_file is None:
            return None
        key = "[registration] matching_file"
        try:
            faces = np.load(r.matching_file, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise self._error(key, f"cannot read {r.matching_file}: {exc}") from exc
        if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
            raise self._error(key, f"must hold an (f, 3) integer array, got {faces.dtype} {faces.shape}")
        ids = self._map_ids(faces.ravel(), key, self._loaded_for(mesh, loaded))
        return ids.reshape(-1, 3)

    # -- helpers ------------------------------------------------------------------------------

    def _loaded_for(self, mesh: TetMesh, loaded: LoadedMesh | None) -> LoadedMesh | None:
        return loaded if loaded is not None else self._loaded.get(mesh.hash)

    def _map_ids(self, ids: Any, key: str, loaded: LoadedMesh | None) -> Array:
        """File node ids -> mesh ids, refusing ids out of range or of dropped nodes."""
        ids = np.asarray(ids, np.int64).ravel()
        if loaded is None:  # no record of loading: the ids are taken as mesh ids
            return ids
        n = loaded.n_source_nodes
        out = ids[(ids < 0) | (ids >= n)]
        if out.size:
            raise self._error(key, f"node ids must lie in 0..{n - 1}, got {out.tolist()[:10]}")
        mapped = loaded.source_to_mesh()[ids]
        if (mapped < 0).any():
            raise self._error(key, f"nodes {ids[mapped < 0].tolist()[:10]} belong to no tet (dropped on loading)")
        return mapped

    def _read_ids(self, path: Path, key: str) -> Array:
        """Node ids from a .npy int array, or a text file with one id a line ('#' comments; a
        UTF-8 BOM, which Windows editors write, skipped)."""
        try:
            if path.suffix == ".npy":
                ids = np.load(path, allow_pickle=False)
            else:
                with warnings.catch_warnings():  # numpy's two-line "no data" warning: refused below
                    warnings.filterwarnings("ignore", "loadtxt: input contained no data", UserWarning)
                    ids = np.loadtxt(path, dtype=np.int64, ndmin=2, comments="#", encoding="utf-8-sig")
        except (OSError, ValueError) as exc:
            raise self._error(key, f"cannot read node ids from {path}: {exc}") from exc
        if not np.issubdtype(ids.dtype, np.integer):
            raise self._error(key, f"{path} must hold integer node ids, got {ids.dtype}")
        # a table's columns would be read as ids, flattened; an array's one row of ids is a list
        # of them, a text file's is not (one id a line)
        if ids.ndim > 1 and ids.size != (max(ids.shape) if path.suffix == ".npy" else len(ids)):
            raise self._error(key, f"{path} holds rows of {ids.size // len(ids)} ids: node ids go one id a line")
        if ids.size == 0:
            raise self._error(key, f"{path} holds no node id")
        return ids.ravel().astype(np.int64)


# -- loading ----------------------------------------------------------------------------------


def _where(loc: tuple) -> str:
    """A pydantic error location as the scene's key: ``[material] nu``, ``name``, ``[boundary]``."""
    if not loc:
        return ""
    head, rest = (f"[{loc[0]}]", loc[1:]) if loc[0] in TABLES else (str(loc[0]), loc[1:])
    key = ""
    for i, part in enumerate(rest):
        key += f"[{part}]" if isinstance(part, int) else (f".{part}" if i else str(part))
    return f"{head} {key}" if key else head


def _describe(err: dict) -> str:
    """One pydantic error as 'key: what is wrong, got what'."""
    kind, ctx, loc = err["type"], err.get("ctx", {}), err["loc"]
    got = repr(err.get("input"))
    got = got if len(got) <= 60 else got[:57] + "..."
    table = len(loc) == 1 and loc[0] in TABLES
    if kind == "missing":
        what = "missing table" if table else "missing (required)"
    elif kind == "extra_forbidden":
        what = "unknown table" if isinstance(err.get("input"), dict) else "unknown key"
    elif kind in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
        op, bound = {
            "greater_than": (">", "gt"),
            "greater_than_equal": (">=", "ge"),
            "less_than": ("<", "lt"),
            "less_than_equal": ("<=", "le"),
        }[kind]
        what = f"must be {op} {ctx[bound]}, got {got}"
    elif kind == "literal_error":
        what = f"must be {ctx['expected']}, got {got}"
    elif kind == "string_pattern_mismatch":
        what = f"{MODEL_ID_RULE}, got {got}"  # the name's, the only pattern
    elif kind == "value_error":
        what = str(ctx.get("error", err["msg"]))
    elif kind == "model_type" or kind == "dict_type":
        what = f"must be a table, got {got}"
    else:
        msg = err["msg"].replace("Input should be", "must be")
        msg = msg.replace("Tuple should", "must").replace("List should", "must")
        what = f"{msg}, got {got}"
    where = _where(loc)
    if kind == "extra_forbidden" and len(loc) == 1 and isinstance(err.get("input"), dict):
        where = f"[{loc[0]}]"
    if kind == "value_error" and what.startswith("["):  # the message names its own key
        return what
    return f"{where}: {what}" if where else what


def parse_scene(text: str, origin: str = "<scene>", base: Path | None = None) -> Scene:
    """A scene from TOML text; relative paths against `base`; errors prefixed with `origin`."""
    try:  # a UTF-8 BOM (Windows editors write one) is no TOML statement: skipped
        data = tomllib.loads(text.removeprefix("\ufeff"))
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{origin}: not valid TOML: {exc}") from exc
    try:
        scene = Scene.model_validate(data, context={"base": base})
    except ValidationError as exc:
        lines = [f"{origin}: {_describe(e)}" for e in exc.errors(include_url=False)]
        raise SceneError("\n".join(lines)) from None
    scene._origin = origin
    return scene


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene file. Raises SceneError naming the file and the bad key."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise SceneError(f"{path}: cannot read the scene file ({exc.strerror or exc})") from exc
    except UnicodeDecodeError as exc:
        raise SceneError(f"{path}: a scene file is TOML in UTF-8 ({exc.reason} at byte {exc.start})") from None
    return parse_scene(text, str(path), path.resolve().parent)


def builtin_scene(name: str) -> Scene:
    """A scene shipped in the package: "beam" (the paper's cantilever) or "phantom" (an organ)."""
    if name not in BUILTIN_SCENES:
        raise SceneError(f"no builtin scene {name!r} (builtins: {', '.join(BUILTIN_SCENES)})")
    res = resources.files("service.scenes").joinpath(f"{name}.toml")
    with resources.as_file(res) as path:
        return parse_scene(path.read_text(encoding="utf-8"), f"builtin:{name}", path.parent)


def resolve_scene(arg: str | Path) -> Scene:
    """A scene from a command-line argument: a .toml path, or the name of a builtin scene."""
    path = Path(arg)
    if path.is_file() or path.suffix == ".toml":
        return load_scene(path)
    if str(arg) in BUILTIN_SCENES:
        return builtin_scene(str(arg))
    raise SceneError(
        f"{arg}: no such scene file, and no builtin scene of that name (builtins: {', '.join(BUILTIN_SCENES)})"
    )


__all__ = [
    "BUILTIN_SCENES",
    "Scene",
    "SceneError",
    "builtin_scene",
    "load_scene",
    "parse_scene",
    "resolve_scene",
]

"""Scenes: the TOML file of SCENES.md, validated into pydantic models, and the mesh it names.

Every key is checked at load time and every error names its key, e.g.
``scene.toml: [material] nu: must be within [0, 0.49999], got 0.6``, so a bad scene fails before hours of
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
- ``[training] keep_off`` or ``keep_off_file``: free surface nodes no training load may touch
  (no patch centres on one or spreads over one); the network still accepts forces there. A test
  at sites held out of the build keeps their supports off (benchmarks/held_out_sites.py).
- ``[registration]``: read by the benchmark and the trainer: ``support`` or ``support_file``
  (node ids where registration may put forces), ``matching_file`` (a .npy (f, 3) array of the
  boundary triangles point clouds lie on).

An id file (``*_file`` but ``matching_file``) is a .npy array or text with one id a line ('#'
comments): two or more ids a line, or none, are refused. A UTF-8 BOM before a scene or an id
file is skipped. Paths (``path`` and every ``*_file`` key) are relative to the TOML file. Node ids in a scene are
the file's ids; when loading drops unused nodes they are mapped onto the mesh's numbering.

Here: :class:`Scene`, the mesh it names, and reading a scene. Its tables are in
:mod:`service.scene.tables`, its node sets resolved in :mod:`service.scene.ids`, its errors in
:mod:`service.scene.errors`, the model id's rule in :mod:`service.scene.model_id`.
"""

from __future__ import annotations

import logging
import tomllib
from importlib import resources
from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import Field, PrivateAttr, ValidationError, model_validator

from ..mesh import MeshError, TetMesh
from ..meshfile import LoadedMesh, ScaleError, load_mesh, mesh_quality, scaled
from . import ids as scene_ids
from .errors import SceneError, describe, scene_error
from .model_id import MODEL_ID
from .tables import (
    FIXED_KEYS,
    BoundarySpec,
    MaterialSpec,
    MeshSpec,
    RegistrationSpec,
    Table,
    TrainingSpec,
    given_keys,
)

log = logging.getLogger("service.scene")  # a scene's warnings under one name, whichever module finds them

Array = np.ndarray

#: Scenes shipped in the package (service/scene/shipped/NAME.toml).
BUILTIN_SCENES = ("beam", "phantom")

#: the span (bounding-box diagonal, m) outside which a mesh is probably in the wrong unit: a
#: finger's width to a torso's
ORGAN_SIZE = (0.01, 2.0)


class Scene(Table):
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
        if self.mesh.path is not None and not given_keys(self.boundary, FIXED_KEYS):
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
        return scene_error(self._origin, key, message)

    # -- mesh ---------------------------------------------------------------------------------

    def load(self) -> LoadedMesh:
        """The scene's mesh, loaded or generated and scaled, before boundary conditions."""
        return self._load()[0]

    def _load(self) -> tuple[LoadedMesh, Array | None]:
        """The loaded mesh, and a generator's default clamp (None for a file)."""
        scale = self.mesh.scale
        if self.mesh.generator is not None:
            from .. import phantoms

            gen = getattr(phantoms, self.mesh.generator)()
            try:
                nodes = scaled(gen.nodes, scale, f"the {self.mesh.generator} generator's mesh", gen.tets)
            except ScaleError as exc:
                raise self._error("[mesh] scale", str(exc)) from exc
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
        except ScaleError as exc:  # the key to change is scale, not path
            raise self._error("[mesh] scale", str(exc)) from exc
        except MeshError as exc:
            raise self._error("[mesh] path", str(exc)) from exc

    def build_mesh(self) -> tuple[TetMesh, LoadedMesh]:
        """The mesh with its fixed nodes resolved, and what loading it found.

        Shape: mesh.fixed (f,) in the mesh's numbering (mapped from the file's ids).
        Refuses a scene that fixes no node, or fixes them at a point or along a line: the
        static problem would be singular (:func:`~service.scene.ids.fixed_nodes`).
        """
        loaded, default_fixed = self._load()
        fixed, key = scene_ids.fixed_nodes(self.boundary, loaded, default_fixed, self._origin)
        mesh = loaded.to_mesh(fixed)
        if mesh.free_surface_nodes.size == 0:  # nothing a tool could push: say so here, not as an empty load region
            what = "every node" if fixed.size == mesh.n_nodes else "every surface node"
            raise self._error(key, f"fixes {what} ({fixed.size} of {mesh.n_nodes} nodes): nothing is left free to load")
        self._loaded[mesh.hash] = loaded
        log.info("%s: %d nodes, %d tets, %d fixed", self._origin, mesh.n_nodes, mesh.n_tets, mesh.fixed.size)
        size = mesh.size
        if not ORGAN_SIZE[0] <= size <= ORGAN_SIZE[1]:  # SCENES.md: metres; a file in mm needs scale 0.001
            log.warning(
                "%s: the mesh spans %.3g m corner to corner, not an organ's %g-%g m: is [mesh] scale right "
                "(a mesh in millimetres needs scale = 0.001)?",
                self._origin,
                size,
                *ORGAN_SIZE,
            )
        return mesh, loaded

    # -- node sets (ids.py) -------------------------------------------------------------

    def region_nodes(self, mesh: TetMesh, loaded: LoadedMesh | None = None) -> Array:
        """Free surface nodes where training loads may be centred (every one by default).

        Shape: (r,) sorted mesh ids.
        `loaded` maps file ids to mesh ids; by default the one `build_mesh` made this mesh from.
        Listed ids must be free surface nodes; box and sphere keep the free surface nodes inside.
        """
        return scene_ids.region_nodes(self.training, mesh, self._loaded_for(mesh, loaded), self._origin)

    def keep_off_nodes(self, mesh: TetMesh, loaded: LoadedMesh | None = None, region: Array | None = None) -> Array:
        """[training] keep_off nodes of the load region (none by default): no training load
        touches them. `region`: region_nodes' answer, where the caller has it. Shape: (k,)
        sorted mesh ids."""
        loaded = self._loaded_for(mesh, loaded)
        return scene_ids.keep_off_nodes(self.training, mesh, loaded, self._origin, region)

    def support_nodes(self, mesh: TetMesh, loaded: LoadedMesh | None = None) -> Array | None:
        """[registration] support nodes in mesh ids, or None when the scene names none.

        Shape: (k,).
        """
        return scene_ids.support_nodes(self.registration, self._loaded_for(mesh, loaded), self._origin)

    def matching_faces(self, mesh: TetMesh, loaded: LoadedMesh | None = None) -> Array | None:
        """[registration] matching triangles in mesh ids, or None when the scene names none.

        Shape: (f, 3).
        """
        return scene_ids.matching_faces(self.registration, self._loaded_for(mesh, loaded), self._origin)

    def _loaded_for(self, mesh: TetMesh, loaded: LoadedMesh | None) -> LoadedMesh | None:
        return loaded if loaded is not None else self._loaded.get(mesh.hash)


# -- loading ----------------------------------------------------------------------------------


def parse_scene(text: str, origin: str = "<scene>", base: Path | None = None) -> Scene:
    """A scene from TOML text; relative paths against `base`; errors prefixed with `origin`."""
    try:  # a UTF-8 BOM (Windows editors write one) is no TOML statement: skipped
        data = tomllib.loads(text.removeprefix("\ufeff"))
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{origin}: not valid TOML: {exc}") from exc
    try:
        scene = Scene.model_validate(data, context={"base": base})
    except ValidationError as exc:
        lines = [f"{origin}: {describe(e)}" for e in exc.errors(include_url=False)]
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
    res = resources.files("service.scene.shipped").joinpath(f"{name}.toml")
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

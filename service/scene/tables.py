"""A scene's tables ([mesh], [material], [boundary], [training], [registration]) as frozen
pydantic models, and the field types they share. The keys and their meaning: SCENES.md and
:mod:`service.scene`; what the node sets resolve to: :mod:`service.scene.ids`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from ..material_range import E_RANGE, NU_RANGE
from ..network_size import MAX_MEMBERS

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


def given_keys(model: BaseModel, keys: tuple[str, ...]) -> list[str]:
    return [k for k in keys if getattr(model, k) is not None]


class Table(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


# -- tables -----------------------------------------------------------------------------------


class MeshSpec(Table):
    """[mesh]: a file (tetrahedral, or a closed surface to tetrahedralise) or a generator."""

    path: ScenePath | None = None
    generator: Literal["beam", "phantom"] | None = None
    scale: Annotated[float, Field(strict=True, gt=0.0, allow_inf_nan=False)] = 1.0

    @model_validator(mode="after")
    def _one_source(self) -> MeshSpec:
        if (self.path is None) == (self.generator is None):
            raise ValueError("give exactly one of path, generator")
        return self


def _within(bounds: tuple[float, float], unit: str = ""):
    """A check that a value lies in [lo, hi], its error naming the range."""

    def check(value: float) -> float:
        if not bounds[0] <= value <= bounds[1]:
            raise ValueError(f"must be within [{bounds[0]:g}, {bounds[1]:g}]{unit}, got {value!r}")
        return value

    return AfterValidator(check)


class MaterialSpec(Table):
    """[material]: the Neo-Hookean law of SCENES.md (the only one), with physical constants."""

    law: Literal["neo-hookean"] = "neo-hookean"
    E: Annotated[float, Field(strict=True, allow_inf_nan=False), _within(E_RANGE, " Pa")]
    nu: Annotated[float, Field(strict=True, allow_inf_nan=False), _within(NU_RANGE)]


FIXED_KEYS = ("fixed_nodes", "fixed_nodes_file", "fixed_box")


class BoundarySpec(Table):
    """[boundary]: the Dirichlet nodes, by id list, id file or box, minus free_nodes."""

    fixed_nodes: list[NodeId] | None = None
    fixed_nodes_file: ScenePath | None = None
    fixed_box: Box | None = None
    free_nodes: list[NodeId] = []

    @model_validator(mode="after")
    def _at_most_one(self) -> BoundarySpec:
        given = given_keys(self, FIXED_KEYS)
        if len(given) > 1:
            raise ValueError(f"give exactly one of {', '.join(FIXED_KEYS)} (got {', '.join(given)})")
        return self


class Sphere(Table):
    centre: Vec3
    radius: Annotated[float, Field(strict=True, gt=0.0, allow_inf_nan=False)]


REGION_KEYS = ("region", "region_file", "region_box", "region_sphere")


class TrainingSpec(Table):
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
    members: Annotated[int, Field(strict=True, ge=1, le=MAX_MEMBERS)] = 1
    keep_off: list[NodeId] | None = None
    keep_off_file: ScenePath | None = None

    @field_validator("patch_nodes")
    @classmethod
    def _ordered(cls, v: tuple[int, int]) -> tuple[int, int]:
        if v[0] > v[1]:
            raise ValueError(f"must be [lo, hi] with lo <= hi, got {list(v)}")
        return v

    @model_validator(mode="after")
    def _at_most_one(self) -> TrainingSpec:
        given = given_keys(self, REGION_KEYS)
        if len(given) > 1:
            raise ValueError(f"give at most one of {', '.join(REGION_KEYS)} (got {', '.join(given)})")
        if self.keep_off is not None and self.keep_off_file is not None:
            raise ValueError("give at most one of keep_off, keep_off_file")
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

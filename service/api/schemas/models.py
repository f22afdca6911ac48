"""The store's models and the forward problem: a model's summary and mesh, and a simulation's
forces in and displacement out."""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import Field, model_validator

from ...registration.settings import ForwardMethod
from .arrays import Finite, ForceValues, NodeIds, Tri, Vec3
from .common import _Reply, _Request


class ForcesIn(_Request):
    nodes: NodeIds = Field(description="(k,) node ids the forces act on")
    values: ForceValues = Field(description="(k, 3) forces, N")

    @model_validator(mode="after")
    def _aligned(self) -> ForcesIn:
        if len(self.nodes) != len(self.values):
            raise ValueError(f"forces: {len(self.nodes)} nodes but {len(self.values)} values")
        return self


class SimulateIn(_Request):
    """The forward problem: displacement under given nodal forces."""

    forces: ForcesIn
    method: ForwardMethod = "network"
    E: Finite | None = Field(None, gt=0, description="Young's modulus, Pa (default: the model's)")


class Material(_Reply):
    law: str
    E: float
    nu: float


class ModelSummary(_Reply):
    id: str
    n_nodes: int
    n_tets: int
    n_surface_nodes: int
    material: Material
    methods: list[ForwardMethod]
    training: dict[str, Any]
    network: dict[str, Any] = {}
    mesh_renumbered: bool = False


class MeshOut(_Reply):
    nodes: list[Vec3]
    tets: list[Annotated[list[int], Field(min_length=4, max_length=4)]]
    surface_faces: list[Tri] = Field(description="outward-oriented boundary triangles")
    surface_nodes: list[int]
    fixed_nodes: list[int]
    region_nodes: list[int] = Field(description="the nodes the network accepts forces on")


class SimulateOut(_Reply):
    displacement: list[Vec3]
    net_force: Vec3
    method: ForwardMethod
    converged: bool
    status: str
    iterations: int
    residual: float | None = Field(
        None,
        description="the FEM's: |f_int(u) - g| / |g| of the returned field under the forces, converged or not "
        "(null: not finite, or status time_limit: not measured past the time cap)",
    )
    error_estimate: float | None = None  # m, the network's: null where infinite (the FEM has residual)
    timing_ms: dict[str, float]

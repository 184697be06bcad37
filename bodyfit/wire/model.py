"""``GET /v1/model`` (gRPC ``GetModelInfo``): what clients need to build requests."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator
from typing_extensions import TypedDict  # pydantic reads typing.TypedDict only from Python 3.12

from bodyfit.wire.base import WireModel


class Dof(WireModel):
    """One coordinate (degree of freedom): OpenSim's name, its range and unit (radians for rotations,
    metres for translations)."""

    name: str
    min: float
    max: float
    unit: Literal["rad", "m"]


class ShapeSizes(WireModel):
    """Shape coefficient counts: ``n_bone`` bone coefficients, then ``n_identity`` identity ones; their sum
    ``n_shape`` (computed when a document leaves it out)."""

    n_bone: int = Field(ge=0)
    n_identity: int = Field(ge=0)
    n_shape: int = Field(ge=0, description="n_bone + n_identity")

    @model_validator(mode="before")
    @classmethod
    def _sum(cls, doc: Any) -> Any:
        if isinstance(doc, dict) and "n_shape" not in doc:
            bone, identity = doc.get("n_bone"), doc.get("n_identity")
            if isinstance(bone, int) and isinstance(identity, int):
                return {**doc, "n_shape": bone + identity}
        return doc

    @model_validator(mode="after")
    def _total(self) -> ShapeSizes:
        if self.n_shape != self.n_bone + self.n_identity:
            raise ValueError(
                f"n_shape {self.n_shape} is not n_bone + n_identity = {self.n_bone + self.n_identity}"
            )
        return self


class MeshSizes(WireModel):
    """The skin mesh: vertex and triangle counts."""

    n_vertices: int = Field(ge=0)
    n_faces: int = Field(ge=0)


class Assets(TypedDict):
    """The model's assets: the asset ``format``, the ``sources`` they were built from and each file's
    ``sha256``."""

    format: str
    sources: dict[str, str]
    sha256: dict[str, str]


class ModelInfo(WireModel):
    """The model a server runs: its DOFs (names, ranges, units), shape sizes, mesh sizes, joint names, the
    package version and the asset hashes.

    The properties give what requests are built from: ``dof_names``, ``dof_ranges`` (n_dof, 2) float64,
    ``dof_units``, ``n_bone``, ``n_identity``, ``n_shape``, ``n_vertices`` and ``n_faces``.
    """

    version: str
    dofs: tuple[Dof, ...]
    shape: ShapeSizes
    mesh: MeshSizes
    joint_names: tuple[str, ...]
    assets: Assets

    @property
    def dof_names(self) -> tuple[str, ...]:
        return tuple(d.name for d in self.dofs)

    @property
    def dof_ranges(self) -> np.ndarray:
        """(n_dof, 2) float64: each DOF's lower and upper limit."""
        return np.array([[d.min, d.max] for d in self.dofs], np.float64).reshape(-1, 2)

    @property
    def dof_units(self) -> tuple[str, ...]:
        return tuple(d.unit for d in self.dofs)

    @property
    def n_bone(self) -> int:
        return self.shape.n_bone

    @property
    def n_identity(self) -> int:
        return self.shape.n_identity

    @property
    def n_shape(self) -> int:
        return self.shape.n_shape

    @property
    def n_vertices(self) -> int:
        return self.mesh.n_vertices

    @property
    def n_faces(self) -> int:
        return self.mesh.n_faces

"""Request bodies of the REST API (pydantic). Unknown keys are refused, so a typo never passes silently, and
types are strict: a number must be a JSON number (an integer is a number; "2" is not), a flag true or
false ("yes" and 1 are not), the batch an integer (2.0 is not). Values and their ranges are checked by
the service core, the same for every transport."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

from bodyfit.wire.arrays import Base64Bytes
from bodyfit.wire.measure import MeasureSex

Format = Literal["npz", "ply", "obj", "glb", "json"]
Matrix = list[list[float]]


class SynthesizeRequest(BaseModel):
    """Parameters of B bodies, or measurements to build the body from. Every field is optional: nothing
    gives the mean body in the zero pose."""

    model_config = ConfigDict(
        extra="forbid",
        strict=True,
        json_schema_extra={
            "examples": [
                {"coordinates": {"knee_angle_r": 1.0, "hip_flexion_r": 0.5}, "format": "npz"},
                {"shape": [[0.5] * 32], "root": [[0.0, 0.95, 0.0]], "skeleton": True, "format": "glb"},
                {
                    "measurements": {"stature": 1.8, "mass": 80.0, "waist": 0.9},
                    "sex": "male",
                    "format": "glb",
                },
            ]
        },
    )

    shape: Matrix | None = Field(
        default=None, description="(B, n_shape) shape coefficients: bone then identity (see GET /v1/model)."
    )
    coordinates: Matrix | dict[str, float | list[float]] | None = Field(
        default=None,
        description="(B, n_dof) coordinates in the order of GET /v1/model's dofs (radians / metres), or "
        "{dof name: value or [B values]}; missing DOFs are 0 (OpenSim's neutral pose).",
    )
    root: Matrix | None = Field(default=None, description="(B, 3) pelvis translation in metres.")
    batch: Annotated[int, Field(ge=1)] | None = Field(
        default=None, description="B when no array gives it (e.g. B mean bodies)."
    )
    skeleton: bool = Field(
        default=False, description="Also pose the bone mesh (npz 'bones'; a second mesh otherwise)."
    )
    format: Format = Field(
        default="npz", description="Response format: npz (fastest), ply, obj, glb or json."
    )
    faces: bool = Field(
        default=False, description="Add the triangles to npz / json (mesh formats always have them)."
    )
    subject: Base64Bytes | None = Field(
        default=None,
        description="Instead of shape: a subject file (the .npz of POST /v1/subjects or `bodyfit rig`), "
        "base64; every body is that person's (their shape and template). Not with shape or measurements.",
    )
    measurements: dict[str, float] | None = Field(
        default=None,
        description="Instead of shape: build the body from these {name: value} in metres (kilograms for "
        "the mass), ANSUR II names or aliases (stature, mass, waist, ...; docs/anthropometry.md), any "
        "subset. The response header Bodyfit-Measurements holds what was requested and achieved.",
    )
    sex: MeasureSex | None = Field(
        default=None, description="With measurements: the plausible ranges and the prior of the built body."
    )

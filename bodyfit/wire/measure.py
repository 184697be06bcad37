"""``POST /v1/measure``: the request (parameters, or measurements to build a body from) and the answer
(anthropometric measurements in SI units; the built body's shape, residuals and unmet measurements).
Measurement names and definitions: docs/anthropometry.md."""

from __future__ import annotations

from typing import Literal

from pydantic import ConfigDict, Field, model_validator

from bodyfit.wire.base import WireModel

MeasureSex = Literal["male", "female"]


class MeasureRequest(WireModel):
    """Either ``shape`` (bodies of the model, with ``coordinates`` optionally) or ``measurements`` (build
    one body from them, with ``sex`` optionally); a mesh in the model's topology goes as a multipart upload
    instead of JSON."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {"shape": [[0.0] * 32]},
                {"measurements": {"stature": 1.8, "mass": 80.0, "waist": 0.9}, "sex": "male"},
            ]
        },
    )

    shape: list[list[float]] | None = Field(
        default=None, description="(B, n_shape) shape coefficients (GET /v1/model) of the bodies to measure."
    )
    coordinates: list[list[float]] | dict[str, float | list[float]] | None = Field(
        default=None,
        description="With shape: (B, n_dof) coordinates or {dof name: value or [B values]}; default the "
        "measuring posture (heights are only meaningful standing).",
    )
    measurements: dict[str, float] | None = Field(
        default=None,
        description="Build a body from these: {name: value} in metres (kilograms for weightkg), ANSUR II "
        "names or aliases (stature, mass, waist, ...); any subset.",
    )
    sex: MeasureSex | None = Field(
        default=None, description="With measurements: the plausible ranges and the prior of the built body."
    )

    @model_validator(mode="after")
    def _one_input(self) -> MeasureRequest:
        if (self.shape is None) == (self.measurements is None):
            raise ValueError("send either shape (bodies to measure) or measurements (a body to build)")
        if self.measurements is not None and self.coordinates is not None:
            raise ValueError("coordinates go with shape; a body built from measurements stands")
        if self.shape is not None and self.sex is not None:
            raise ValueError("sex goes with measurements; a body given by its shape is measured as it is")
        return self


class MeasurementInfo(WireModel):
    """One measurement's ``name`` (its ANSUR II column where the survey has it), ``kind`` (height, length,
    breadth, circumference or mass) and ``unit`` ("m" or "kg")."""

    name: str
    kind: str
    unit: str


class Measurements(WireModel):
    """The answer of ``POST /v1/measure``.

    ``values``: name -> B values (one per body measured; one for a built body), in metres (kilograms for
    ``weightkg``); ``measurements`` describes each name, in the same order. For a body built from
    measurements: ``shape`` (1, n_shape), ``residuals`` (achieved minus requested, for the measurements
    requested), ``unmet`` (the requested ones missed by more than their tolerance) and ``flagged`` (some
    are unmet: the set cannot all be met in the model's shape space; the body is the best compromise)."""

    measurements: list[MeasurementInfo] = Field(
        default_factory=list, description="Each name's kind and unit (left out of synthesize's header)."
    )
    values: dict[str, list[float]]
    shape: list[list[float]] | None = None
    requested: dict[str, float] | None = None
    residuals: dict[str, float] | None = None
    unmet: list[str] = Field(default_factory=list)
    flagged: bool = False

"""The small documents: liveness, readiness and a synthesis answered as JSON."""

from __future__ import annotations

from typing import Literal

from bodyfit.wire.base import WireModel

Rows = list[list[float | None]]
Batch = list[list[list[float | None]]]


class Health(WireModel):
    """``GET /healthz``: the process serves requests."""

    status: Literal["ok"] = "ok"


class Ready(WireModel):
    """``GET /readyz`` with 200: the model is loaded (a 503 answers a :class:`~bodyfit.wire.Problem`)."""

    status: Literal["ready"] = "ready"


class SynthesisJSON(WireModel):
    """``POST /v1/synthesize`` with ``"format": "json"``: B posed bodies as nested lists. vertices
    (B, V, 3) and joints (B, J, 3) metres, with ``joint_names``; faces (F, 3) when asked for; bones
    (B, Vb, 3) with the skeleton, and bone_faces (Fb, 3) with the skeleton and faces."""

    vertices: Batch
    joints: Batch
    joint_names: list[str]
    faces: list[list[int]] | None = None
    bones: Batch | None = None
    bone_faces: list[list[int]] | None = None

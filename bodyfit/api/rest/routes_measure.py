"""POST /v1/measure: anthropometric measurements (docs/anthropometry.md) of bodies given by their
parameters (JSON), of a mesh in the model's topology (multipart upload), or of a body built from
measurements (JSON), answered as :class:`bodyfit.wire.measure.Measurements`."""

from __future__ import annotations

from pathlib import PurePath
from typing import Any

import numpy as np
from fastapi import APIRouter, FastAPI, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError
from starlette.datastructures import UploadFile

from bodyfit.api.rest.openapi import PROBLEMS
from bodyfit.api.rest.state import Service
from bodyfit.service.core import SynthRequest
from bodyfit.service.errors import InvalidInputError
from bodyfit.service.synthesis import rows_array
from bodyfit.wire.measure import Measurements, MeasureRequest

router = APIRouter(prefix="/v1", tags=["anthropometry"])

_UPLOAD = {
    "type": "object",
    "required": ["file"],
    "properties": {
        "file": {
            "type": "string",
            "format": "binary",
            "description": "A mesh in the model's topology (GET /v1/model: mesh.n_vertices), standing on +y: "
            ".npz (vertices) or .ply",
        },
        "units": {"type": "string", "enum": ["auto", "m", "mm"], "default": "m"},
    },
}
_BODY = {
    "required": True,
    "content": {
        "application/json": {"schema": MeasureRequest.model_json_schema()},
        "multipart/form-data": {"schema": _UPLOAD},
    },
}


@router.post(
    "/measure",
    summary="Measurements of bodies (parameters or a mesh in our topology), or a body from measurements",
    response_model=Measurements,
    responses={**PROBLEMS},
    openapi_extra={"requestBody": _BODY},
)
async def measure(request: Request, service: Service) -> Measurements:
    kind = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if kind == "multipart/form-data":
        vertices = await _uploaded_vertices(request, service)
        return await run_in_threadpool(service.measure, vertices=vertices)
    body = _request(await request.body())
    if body.measurements is not None:
        return await run_in_threadpool(service.measure, measurements=body.measurements, sex=body.sex)
    coords = body.coordinates
    synth = SynthRequest(
        shape=rows_array(body.shape, "shape"),
        coordinates=coords if isinstance(coords, dict) else rows_array(coords, "coordinates"),
    )
    return await run_in_threadpool(service.measure, synth)


def _request(data: bytes) -> MeasureRequest:
    """The JSON body read as :class:`MeasureRequest`; a malformed one is refused like FastAPI's own bodies
    (a 422 problem naming the field)."""
    try:
        return MeasureRequest.model_validate_json(data or b"null")
    except ValidationError as exc:
        errors: list[Any] = [{**e, "loc": ("body", *e["loc"])} for e in exc.errors(include_url=False)]
        raise RequestValidationError(errors) from None


async def _uploaded_vertices(request: Request, service: Service) -> np.ndarray:
    """The (V, 3) vertices of the uploaded mesh, in metres."""
    form = await request.form()
    upload = form.get("file")
    if not isinstance(upload, UploadFile):
        raise InvalidInputError("send the mesh as the multipart field 'file' (.npz or .ply)", "file")
    units = form.get("units", "m")
    if units not in ("auto", "m", "mm"):
        raise InvalidInputError(f"units must be auto, m or mm; got {units!r}", "units")
    fmt = PurePath(upload.filename or "").suffix.lstrip(".")
    if not fmt:
        raise InvalidInputError("the file name has no suffix; name it .npz or .ply", "file")
    scan = await run_in_threadpool(service.read_scan, await upload.read(), fmt, str(units))
    return scan.points


def install(app: FastAPI) -> None:
    """Mount ``POST /v1/measure`` on ``app``."""
    app.include_router(router)

"""POST /v1/synthesize: parameters -> posed mesh, joints and skeleton (ONNX Runtime)."""

from __future__ import annotations

import asyncio

import numpy as np
from fastapi import APIRouter, Response
from fastapi.concurrency import run_in_threadpool

from bodyfit.api.rest.openapi import PROBLEMS
from bodyfit.api.rest.state import Service
from bodyfit.api.schemas import SynthesizeRequest
from bodyfit.service.core import SynthRequest
from bodyfit.service.errors import InvalidInputError
from bodyfit.service.formats import MEDIA_TYPES, encode_bodies
from bodyfit.wire import SynthesisJSON

router = APIRouter(prefix="/v1", tags=["synthesis"])


def _array(value: list[list[float]] | None, field: str) -> np.ndarray | None:
    if value is None:
        return None
    rows = {len(row) for row in value}
    if len(rows) > 1:
        raise InvalidInputError(
            f"the rows of {field} have different lengths {sorted(rows)}; send a (B, N) matrix", field
        )
    return np.asarray(value, np.float64)


@router.post(
    "/synthesize",
    summary="Parameters -> posed skin (and skeleton) as npz, ply, obj, glb or json",
    response_class=Response,
    responses={
        200: {
            "model": SynthesisJSON,
            "description": "The posed bodies in the format asked for (json: the schema below)",
            "content": {t: {} for t in MEDIA_TYPES.values() if t != "application/json"},
        },
        **PROBLEMS,
    },
)
async def synthesize(body: SynthesizeRequest, service: Service) -> Response:
    coords = body.coordinates
    request = SynthRequest(
        shape=_array(body.shape, "shape"),
        coordinates=coords if isinstance(coords, dict) else _array(coords, "coordinates"),
        root=_array(body.root, "root"),
        skeleton=body.skeleton,
        batch=body.batch,
    )
    pending = service.start_synthesis(request)  # validates here; the model call joins the next batch
    vertices, joints = await asyncio.wrap_future(pending.future)

    def encode() -> bytes:
        return encode_bodies(
            service.finish_synthesis(pending, vertices, joints), body.format, faces=body.faces
        )

    # npz of a plain body takes a fraction of a millisecond; meshes, text and the skeleton go to a thread.
    light = body.format == "npz" and not body.skeleton and len(vertices) <= 8
    data = encode() if light else await run_in_threadpool(encode)
    return Response(data, media_type=MEDIA_TYPES[body.format])

"""POST /v1/synthesize: parameters, or measurements to build the body from -> posed mesh, joints and
skeleton (ONNX Runtime)."""

from __future__ import annotations

import asyncio

from fastapi import APIRouter, Response
from fastapi.concurrency import run_in_threadpool

from bodyfit.api.rest.openapi import PROBLEMS
from bodyfit.api.rest.state import Service
from bodyfit.api.schemas import SynthesizeRequest
from bodyfit.service.core import SynthRequest
from bodyfit.service.formats import MEDIA_TYPES, encode_bodies
from bodyfit.service.synthesis import rows_array
from bodyfit.wire import SynthesisJSON

router = APIRouter(prefix="/v1", tags=["synthesis"])

BUILT_HEADER = "Bodyfit-Measurements"
"""The response header that carries, for a body built from measurements, its
:class:`~bodyfit.wire.measure.Measurements` document (requested, achieved, residuals, unmet) as JSON,
without the per-name descriptions (docs/anthropometry.md) so that it stays within 4 KB, the smallest
response-header buffer of common proxies."""


@router.post(
    "/synthesize",
    summary="Parameters or measurements -> posed skin (and skeleton) as npz, ply, obj, glb or json",
    response_class=Response,
    responses={
        200: {
            "model": SynthesisJSON,
            "description": "The posed bodies in the format asked for (json: the schema below). A body built "
            f"from measurements has the {BUILT_HEADER} header: its measurements document as JSON",
            "content": {t: {} for t in MEDIA_TYPES.values() if t != "application/json"},
        },
        **PROBLEMS,
    },
)
async def synthesize(body: SynthesizeRequest, service: Service) -> Response:
    coords = body.coordinates
    request = SynthRequest(
        shape=rows_array(body.shape, "shape"),
        coordinates=coords if isinstance(coords, dict) else rows_array(coords, "coordinates"),
        root=rows_array(body.root, "root"),
        skeleton=body.skeleton,
        batch=body.batch,
        measurements=body.measurements,
        sex=body.sex,
        subject=body.subject,
    )
    headers = {}
    if request.measurements is not None or request.sex is not None:
        request, built = await run_in_threadpool(service.with_built_shape, request)
        if built is not None:
            headers[BUILT_HEADER] = built.model_dump_json(exclude={"measurements"})
    if request.subject is None:
        pending = service.start_synthesis(request)  # validates here; the model call joins the next batch
    else:  # the subject's decoder poses the bodies at once: off the event loop
        pending = await run_in_threadpool(service.start_synthesis, request)
    vertices, joints = await asyncio.wrap_future(pending.future)

    def encode() -> bytes:
        return encode_bodies(
            service.finish_synthesis(pending, vertices, joints), body.format, faces=body.faces
        )

    # npz of a plain body takes a fraction of a millisecond; meshes, text and the skeleton go to a thread.
    light = body.format == "npz" and not body.skeleton and len(vertices) <= 8
    data = encode() if light else await run_in_threadpool(encode)
    return Response(data, media_type=MEDIA_TYPES[body.format], headers=headers)

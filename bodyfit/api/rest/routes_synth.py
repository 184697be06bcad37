"""POST /v1/synthesize: parameters -> posed mesh, joints and skeleton (ONNX Runtime)."""

from __future__ import annotations

import numpy as np
from fastapi import APIRouter, Response

from bodyfit.api.rest.state import Service
from bodyfit.api.schemas import SynthesizeRequest
from bodyfit.service.core import SynthRequest
from bodyfit.service.errors import InvalidInputError
from bodyfit.service.formats import MEDIA_TYPES, encode_bodies

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
    responses={200: {"content": {t: {} for t in MEDIA_TYPES.values()}}},
)
def synthesize(body: SynthesizeRequest, service: Service) -> Response:
    coords = body.coordinates
    request = SynthRequest(
        shape=_array(body.shape, "shape"),
        coordinates=coords if isinstance(coords, dict) else _array(coords, "coordinates"),
        root=_array(body.root, "root"),
        skeleton=body.skeleton,
        batch=body.batch,
    )
    data = encode_bodies(service.synthesize(request), body.format, faces=body.faces)
    return Response(data, media_type=MEDIA_TYPES[body.format])

"""GET /v1/model: what clients need to build requests."""

from __future__ import annotations

from fastapi import APIRouter

from bodyfit.api.rest.openapi import PROBLEMS
from bodyfit.api.rest.state import Service
from bodyfit.wire import ModelInfo

router = APIRouter(prefix="/v1", tags=["model"])


@router.get(
    "/model",
    summary="Model info: DOF names, ranges and units, shape sizes, joints, asset hashes",
    response_model=ModelInfo,
    responses=PROBLEMS,
)
def model_info(service: Service) -> ModelInfo:
    return service.info()

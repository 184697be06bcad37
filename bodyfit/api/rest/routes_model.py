"""GET /v1/model: what clients need to build requests."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

from bodyfit.api.rest.state import Service

router = APIRouter(prefix="/v1", tags=["model"])


@router.get("/model", summary="Model info: DOF names, ranges and units, shape sizes, joints, asset hashes")
def model_info(service: Service) -> dict[str, Any]:
    return service.info().to_dict()

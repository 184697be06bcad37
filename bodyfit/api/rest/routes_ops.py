"""Operations: /healthz (the process answers), /readyz (the model is loaded), /metrics (Prometheus)."""

from __future__ import annotations

from fastapi import APIRouter, Response
from fastapi.responses import JSONResponse

from bodyfit.api import problems
from bodyfit.api.rest.openapi import PROBLEMS
from bodyfit.api.rest.state import State
from bodyfit.wire import Health, Ready

router = APIRouter(tags=["operations"])


@router.get("/healthz", summary="Liveness: 200 while the process serves requests", response_model=Health)
def healthz() -> Health:
    return Health()


@router.get(
    "/readyz",
    summary="Readiness: 200 once the model is loaded, else 503",
    response_model=None,
    responses={200: {"model": Ready, "description": "The model is loaded"}, **PROBLEMS},
)
def readyz(state: State) -> JSONResponse:
    if state.service is not None:
        return JSONResponse(Ready().model_dump(mode="json"))
    detail = state.load_error or "the model is loading"
    return problems.response(problems.problem("unavailable", "Not ready", detail, 503))


@router.get("/metrics", summary="Prometheus metrics", response_class=Response)
def metrics(state: State) -> Response:
    return Response(state.metrics.exposition(), media_type="text/plain; version=0.0.4")

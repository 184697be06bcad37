"""Operations: /healthz (the process answers), /readyz (the model is loaded), /metrics (Prometheus)."""

from __future__ import annotations

from fastapi import APIRouter, Response
from fastapi.responses import JSONResponse

from bodyfit.api import problems
from bodyfit.api.rest.state import State

router = APIRouter(tags=["operations"])


@router.get("/healthz", summary="Liveness: 200 while the process serves requests")
def healthz() -> dict[str, str]:
    return {"status": "ok"}


@router.get("/readyz", summary="Readiness: 200 once the model is loaded, else 503")
def readyz(state: State) -> JSONResponse:
    if state.service is not None:
        return JSONResponse({"status": "ready"})
    detail = state.load_error or "the model is loading"
    return problems.response(problems.problem("unavailable", "Not ready", detail, 503))


@router.get("/metrics", summary="Prometheus metrics", response_class=Response)
def metrics(state: State) -> Response:
    return Response(state.metrics.exposition(), media_type="text/plain; version=0.0.4")

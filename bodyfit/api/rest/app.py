"""The FastAPI application: ``create_app(settings)`` for uvicorn, or ``create_app(service=...)`` over an
already loaded core (tests, in-process use)."""

from __future__ import annotations

import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI

from bodyfit.api import problems
from bodyfit.api.metrics import Metrics
from bodyfit.api.rest import (
    openapi,
    routes_fit,
    routes_measure,
    routes_model,
    routes_ops,
    routes_subjects,
    routes_synth,
    routes_upgrade,
    routes_viewer,
)
from bodyfit.api.rest.limits import BodyLimit
from bodyfit.api.rest.measured import Measured
from bodyfit.api.rest.state import AppState
from bodyfit.api.settings import ServiceSettings
from bodyfit.service.core import BodyService

DESCRIPTION = """Parametric human bodies with a biomechanical skeleton inside.

Errors are RFC 7807 problem+json documents whose `detail` says what was wrong and how to fix it, with
`kind` (also used by gRPC) and `field`. Long work (fits, upgrades) streams NDJSON when asked with
`Accept: application/x-ndjson`; closing the connection cancels it. The answers and events are the models of
`bodyfit.wire`, shared with the Python SDK."""


def create_app(
    settings: ServiceSettings | None = None,
    service: BodyService | None = None,
    metrics: Metrics | None = None,
) -> FastAPI:
    """The app. With ``service`` given it is ready at once; otherwise the model loads in a background
    thread at start-up (``/healthz`` answers meanwhile, ``/readyz`` turns 200 when loaded). ``metrics``:
    shared with a gRPC server in the same process, so /metrics shows both."""
    settings = settings or ServiceSettings()
    state = AppState(settings, metrics=metrics or Metrics(), service=service)
    if service is not None:
        state.loaded.set()

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        if not state.loaded.is_set():
            threading.Thread(target=state.load, name="bodyfit-load", daemon=True).start()
        yield

    app = FastAPI(
        title="bodyfit",
        version="1",
        description=DESCRIPTION,
        lifespan=lifespan,
        openapi_url="/openapi.json",
    )
    app.state.bodyfit = state
    problems.install(app)
    openapi.install(app)
    for router in (
        routes_model.router,
        routes_synth.router,
        routes_fit.router,
        routes_upgrade.router,
        routes_subjects.router,
        routes_ops.router,
    ):
        app.include_router(router)
    routes_measure.install(app)  # POST /v1/measure: anthropometry of bodies, or a body from measurements
    routes_viewer.install(app)  # the browser viewer at / and /viewer

    app.add_middleware(BodyLimit, max_bytes=settings.limits().max_upload_bytes)
    app.add_middleware(Measured, metrics=state.metrics)  # outermost: sees refused uploads too
    return app

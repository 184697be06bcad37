"""The app's state: settings, the service core (loaded once, in the background at start-up) and metrics."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Annotated

from fastapi import Depends, Request

from bodyfit.api.metrics import Metrics
from bodyfit.api.settings import ServiceSettings
from bodyfit.service.core import BodyService
from bodyfit.service.errors import BusyError


@dataclass
class AppState:
    """``service`` is None until loading finished; ``load_error`` says why loading failed."""

    settings: ServiceSettings
    metrics: Metrics = field(default_factory=Metrics)
    service: BodyService | None = None
    load_error: str | None = None
    loaded: threading.Event = field(default_factory=threading.Event)

    def load(self) -> None:
        """Build the service (runs in a background thread; /readyz turns 200 when done)."""
        try:
            s = self.settings
            self.service = BodyService.load(
                s.assets, s.limits(), s.threads, smpl_model=s.smpl_model, scan_processes=s.scan_processes
            )
        except Exception as exc:  # surfaced by /readyz and every request, never raised into the loop
            self.load_error = f"{type(exc).__name__}: {exc}"
        finally:
            self.loaded.set()

    def ready_service(self) -> BodyService:
        if self.service is not None:
            return self.service
        if self.load_error is not None:
            raise BusyError(f"the model failed to load: {self.load_error}")
        raise BusyError("the model is still loading; retry in a few seconds (GET /readyz says when)")


async def app_state(request: Request) -> AppState:
    state: AppState = request.app.state.bodyfit
    return state


async def ready_service(request: Request) -> BodyService:
    # async: FastAPI would run a plain function in its thread pool, a hop per request
    state: AppState = request.app.state.bodyfit
    return state.ready_service()


Service = Annotated[BodyService, Depends(ready_service)]
State = Annotated[AppState, Depends(app_state)]

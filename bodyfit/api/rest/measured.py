"""ASGI middleware recording each request in the server's Prometheus metrics (operation = route path)."""

from __future__ import annotations

import time

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from bodyfit.api.metrics import Metrics


class Measured:
    """Counts requests by route and status, observes their latency and tracks those in flight."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        m = self.metrics
        status = 500
        began = time.perf_counter()

        async def recorded(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
            await send(message)

        m.in_flight.labels("rest").inc()
        try:
            await self.app(scope, receive, recorded)
        finally:
            route = scope.get("route")
            operation = getattr(route, "path", "unmatched")
            m.in_flight.labels("rest").dec()
            m.latency.labels("rest", operation).observe(time.perf_counter() - began)
            m.requests.labels("rest", operation, str(status)).inc()

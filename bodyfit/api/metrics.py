"""Prometheus metrics of one server (its own registry: no process-global state)."""

from __future__ import annotations

from dataclasses import dataclass, field

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.process_collector import ProcessCollector

LATENCY_BUCKETS = (0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 120.0)


@dataclass
class Metrics:
    """Requests by transport, operation and outcome; latency histograms; requests in flight; the process's
    memory and CPU (``process_*``)."""

    registry: CollectorRegistry = field(default_factory=CollectorRegistry)

    def __post_init__(self) -> None:
        r = self.registry
        ProcessCollector(registry=r)
        self.requests = Counter(
            "bodyfit_requests", "Requests served", ["transport", "operation", "outcome"], registry=r
        )
        self.latency = Histogram(
            "bodyfit_request_seconds",
            "Request latency",
            ["transport", "operation"],
            buckets=LATENCY_BUCKETS,
            registry=r,
        )
        self.in_flight = Gauge(
            "bodyfit_requests_in_flight", "Requests being served", ["transport"], registry=r
        )

    def exposition(self) -> bytes:
        return generate_latest(self.registry)

"""Property-based requests generated from the published OpenAPI document (schemathesis): no request the
schema allows, nor its negative variants, makes the server answer with a 5xx; every refusal is a
problem document with a detail."""

from __future__ import annotations

from typing import Any

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.generation import GenerationMode

from bodyfit.api.rest.app import create_app
from bodyfit.api.settings import ServiceSettings
from bodyfit.service.core import BodyService

OPERATIONS = [
    ("GET", "/v1/model"),
    ("POST", "/v1/synthesize"),
    ("POST", "/v1/fit/scan"),
    ("POST", "/v1/fit/sequence"),
    ("POST", "/v1/upgrade"),
    ("POST", "/v1/measure"),
    ("POST", "/v1/subjects"),
    ("GET", "/healthz"),
    ("GET", "/readyz"),
]


@pytest.fixture(scope="module")
def api_schema(body_service: BodyService) -> Any:
    app = create_app(ServiceSettings(max_upload_mb=1.0), service=body_service)
    return schemathesis.openapi.from_asgi("/openapi.json", app)


def test_every_operation_is_fuzzed(api_schema: Any) -> None:
    published = {(op.ok().method.upper(), op.ok().path) for op in api_schema.get_all_operations()}
    assert published - {("GET", "/metrics")} == set(OPERATIONS)


CASES = [
    pytest.param(method, path, mode, id=f"{label} {method} {path}")
    for method, path in OPERATIONS
    for mode, label in ((GenerationMode.POSITIVE, "valid"), (GenerationMode.NEGATIVE, "invalid"))
    if method == "POST" or mode == GenerationMode.POSITIVE  # a GET without parameters has no invalid form
]


@pytest.mark.parametrize(("method", "path", "mode"), CASES)
def test_no_server_errors(api_schema: Any, method: str, path: str, mode: GenerationMode) -> None:
    operation = api_schema[path][method]

    @given(case=operation.as_strategy(generation_mode=mode))
    @settings(max_examples=25, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
    def check(case: Any) -> None:
        response = case.call()
        assert response.status_code < 500, f"{method} {path}: {response.status_code} {response.text[:500]}"
        if response.status_code >= 400:
            media = response.headers.get("content-type", [""])[0]
            assert media.startswith("application/problem+json"), response.text
            assert response.json()["detail"]

    check()

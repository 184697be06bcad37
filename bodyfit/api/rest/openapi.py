"""The wire models in the OpenAPI document: the JSON answers as response models, the NDJSON events as the
discriminated unions of :mod:`bodyfit.wire`, and every error as a problem document."""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI
from pydantic import BaseModel, TypeAdapter

from bodyfit import wire as w
from bodyfit.wire.subjects import SUBJECT_EVENTS

NDJSON = "application/x-ndjson"
PROBLEM_MEDIA_TYPE = "application/problem+json"
COMPONENTS = "#/components/schemas/{model}"
STREAMS: dict[str, TypeAdapter[Any]] = {
    "ScanFitEvent": w.SCAN_EVENTS,
    "SequenceFitEvent": w.SEQUENCE_EVENTS,
    "UpgradeEvent": w.UPGRADE_EVENTS,
    "SubjectEvent": SUBJECT_EVENTS,
    "Problem": TypeAdapter(w.Problem),
}
"""The schemas no route declares as its response model, added to the document's components."""


def _ref(name: str) -> dict[str, str]:
    return {"$ref": COMPONENTS.format(model=name)}


PROBLEMS: dict[int | str, dict[str, Any]] = {
    status: {
        "description": f"{what}: an RFC 7807 problem document whose detail says what was wrong and the fix",
        "content": {PROBLEM_MEDIA_TYPE: {"schema": _ref("Problem")}},
    }
    for status, what in (("4XX", "Refused"), ("5XX", "Not ready, too late or a bug"))
}
"""Every route's errors."""


def streamed(answer: type[BaseModel], events: str, what: str) -> dict[int | str, dict[str, Any]]:
    """The responses of a route that answers ``answer`` as JSON, or the ``events`` stream (a name in
    :data:`STREAMS`) as NDJSON when asked for with ``Accept: application/x-ndjson``."""
    return {
        200: {
            "model": answer,
            "description": f"{what}. With Accept: application/x-ndjson, one event per line instead: progress "
            "events, then chunk events (sequences and upgrades), then the result; a failure midway is an "
            "error event.",
            "content": {NDJSON: {"schema": _ref(events)}},
        },
        **PROBLEMS,
    }


def with_streams(spec: dict[str, Any]) -> dict[str, Any]:
    """``spec`` (an OpenAPI document) with the schemas of :data:`STREAMS` and the models they use among its
    components (those already there are kept)."""
    schemas = spec.setdefault("components", {}).setdefault("schemas", {})
    modes = [(name, "serialization", adapter) for name, adapter in STREAMS.items()]
    tops, defs = TypeAdapter.json_schemas(modes, ref_template=COMPONENTS)  # type: ignore[arg-type]
    for name, schema in defs.get("$defs", {}).items():
        schemas.setdefault(name, schema)
    for (name, _), schema in tops.items():
        if schema != _ref(name):  # a model's own schema is among the $defs already
            schemas[name] = schema
    return spec


def install(app: FastAPI) -> None:
    """Make ``app``'s OpenAPI document (built on its first request) carry the schemas of :data:`STREAMS`."""
    build = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = with_streams(build())
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]

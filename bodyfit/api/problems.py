"""RFC 7807 problem+json responses for every error REST returns; no stack trace ever reaches a client."""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException

from bodyfit import wire as w
from bodyfit.models.errors import BodyfitError
from bodyfit.service.errors import ServiceError, as_service_error

LOG = logging.getLogger("bodyfit.api")
MEDIA_TYPE = "application/problem+json"
STATUS = {
    "invalid_argument": 422,
    "resource_exhausted": 413,
    "unavailable": 503,
    "deadline_exceeded": 504,
    "cancelled": 499,
    "not_found": 404,
    "internal": 500,
}
_KIND_OF_STATUS = {400: "invalid_argument", 404: "not_found", 405: "not_found", 413: "resource_exhausted"}


def problem(kind: str, title: str, detail: str, status: int, field: str | None = None) -> dict[str, Any]:
    """The problem document (:class:`bodyfit.wire.Problem`): RFC 7807 members plus ``kind`` (shared with
    gRPC) and ``field`` (left out when there is none)."""
    doc = w.Problem.model_validate(
        {
            "type": f"https://bodyfit.dev/problems/{kind}",
            "title": title,
            "status": status,
            "detail": detail,
            "kind": kind,
            "field": field,
        }
    )
    return doc.model_dump(exclude_none=True)


def service_problem(exc: ServiceError) -> dict[str, Any]:
    return problem(exc.kind, exc.title, exc.detail, STATUS.get(exc.kind, 500), exc.field)


def response(doc: dict[str, Any], headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse(doc, status_code=int(doc["status"]), media_type=MEDIA_TYPE, headers=headers)


def install(app: FastAPI) -> None:
    """Register the exception handlers on ``app``."""

    @app.exception_handler(ServiceError)
    async def on_service_error(_: Request, exc: ServiceError) -> JSONResponse:
        headers = {"Retry-After": "5"} if exc.kind == "unavailable" else None
        return response(service_problem(exc), headers)

    @app.exception_handler(BodyfitError)
    async def on_model_error(request: Request, exc: BodyfitError) -> JSONResponse:
        # the model layer's input errors are the client's (422); a broken asset is the server's (500)
        error = as_service_error(exc)
        if error is None:
            return await on_bug(request, exc)
        return response(service_problem(error))

    @app.exception_handler(RequestValidationError)
    async def on_validation(_: Request, exc: RequestValidationError) -> JSONResponse:
        errors = exc.errors()
        first = errors[0] if errors else {}
        where = ".".join(str(p) for p in first.get("loc", ()) if p not in ("body", "query"))
        if first.get("type") == "json_invalid":
            detail = (
                f"the request body is not valid JSON ({first.get('ctx', {}).get('error', 'parse error')})"
            )
            return response(problem("invalid_argument", "Invalid request", detail, 422))
        lines = [
            f"{'.'.join(str(p) for p in e.get('loc', ()) if p not in ('body', 'query'))}: {e.get('msg')}"
            for e in errors[:5]
        ]
        detail = "; ".join(lines) + ". See the OpenAPI schema at /docs for the expected request."
        return response(problem("invalid_argument", "Invalid request", detail, 422, where or None))

    @app.exception_handler(HTTPException)
    async def on_http(_: Request, exc: HTTPException) -> JSONResponse:
        kind = _KIND_OF_STATUS.get(
            exc.status_code, "invalid_argument" if exc.status_code < 500 else "internal"
        )
        return response(problem(kind, "Request refused", str(exc.detail), exc.status_code))

    @app.exception_handler(Exception)
    async def on_bug(request: Request, exc: Exception) -> JSONResponse:
        LOG.exception("unhandled error on %s %s", request.method, request.url.path)
        detail = "the server failed unexpectedly; the error is logged on the server. Please report it."
        return response(problem("internal", "Internal error", detail, 500))

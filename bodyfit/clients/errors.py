"""Typed exceptions the SDK raises, built from the server's error body (REST problem+json or a gRPC
status). ``kind`` is the wire name shared by both transports: invalid_argument, resource_exhausted,
unavailable, deadline_exceeded, cancelled, not_found, internal."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from pydantic import ValidationError

from bodyfit.wire import GRPC_STATUS_KINDS


class BodyfitClientError(Exception):
    """Base class. ``status``: the HTTP status (or the gRPC code's name); ``detail``: what was wrong and
    how to fix it; ``field``: the request field at fault, when known; ``retryable``: safe to send again
    (for an idempotent call); ``retry_after``: seconds the server asked to wait before that, when it said;
    ``sent``: False only when the request surely never reached the server (safe to send again whatever
    the call)."""

    kind = "internal"
    retryable = False

    def __init__(
        self,
        detail: str,
        status: int | str | None = None,
        field: str | None = None,
        *,
        retry_after: float | None = None,
        sent: bool = True,
    ) -> None:
        super().__init__(detail if field is None else f"{field}: {detail}")
        self.detail = detail
        self.status = status
        self.field = field
        self.retry_after = retry_after
        self.sent = sent


class InvalidRequestError(BodyfitClientError):
    """The request was malformed or out of range; fix it (never retried)."""

    kind = "invalid_argument"


class RequestTooLargeError(BodyfitClientError):
    """Larger than the server's limits (upload size, points, frames, batch)."""

    kind = "resource_exhausted"


class ServerBusyError(BodyfitClientError):
    """The server had no free worker or is not ready; retried with backoff by the clients."""

    kind = "unavailable"
    retryable = True


class RequestTimeoutError(BodyfitClientError):
    """The work ran past the server's time limit or the client's timeout."""

    kind = "deadline_exceeded"


class RequestCancelledError(BodyfitClientError):
    """The request was cancelled."""

    kind = "cancelled"


class NotFoundError(BodyfitClientError):
    """No such operation (wrong URL or an older server)."""

    kind = "not_found"


class ServerError(BodyfitClientError):
    """The server failed unexpectedly (a bug; the server's logs have the details)."""

    kind = "internal"


class ConnectionFailedError(BodyfitClientError):
    """The server could not be reached."""

    kind = "unavailable"
    retryable = True


ERRORS: dict[str, type[BodyfitClientError]] = {
    cls.kind: cls
    for cls in (
        InvalidRequestError,
        RequestTooLargeError,
        ServerBusyError,
        RequestTimeoutError,
        RequestCancelledError,
        NotFoundError,
        ServerError,
    )
}


HTTP_KINDS = {413: "resource_exhausted", 404: "not_found", 503: "unavailable", 504: "deadline_exceeded"}
"""The kind of an HTTP status without a problem document (a proxy's answer); else 4xx invalid_argument,
5xx internal."""
_NOT_SENT = ("failed to connect", "connection refused", "dns resolution failed", "name resolution")
"""Words of gRPC's UNAVAILABLE details when no connection was made, so the request never left."""


def error_from_problem(
    problem: dict[str, Any], status: int | str | None, retry_after: float | None = None
) -> BodyfitClientError:
    """The typed exception for a problem document ``{"kind", "detail", "field", ...}``."""
    cls = ERRORS.get(str(problem.get("kind", "")), ServerError)
    detail = str(problem.get("detail") or problem.get("title") or "the server gave no detail")
    field = problem.get("field")
    return cls(detail, status, None if field is None else str(field), retry_after=retry_after)


def error_from_http(status: int, body: bytes, retry_after: float | None = None) -> BodyfitClientError:
    """The typed exception of a non-2xx answer: its problem+json, or plain text from a proxy."""
    try:
        doc = json.loads(body)
    except (json.JSONDecodeError, UnicodeDecodeError):
        doc = {}
    if not isinstance(doc, dict) or "kind" not in doc:
        kind = HTTP_KINDS.get(status, "invalid_argument" if status < 500 else "internal")
        text = body[:300].decode("utf-8", "replace")
        doc = {"kind": kind, "detail": f"HTTP {status}: {text}"}
    return error_from_problem(doc, status, retry_after)


def error_from_status(
    code: str, details: str, trailing: Mapping[str, Any], retry_after: float | None = None
) -> BodyfitClientError:
    """The typed exception of a gRPC status: ``code`` its name, ``trailing`` its metadata (the server's
    "bodyfit-kind" and "bodyfit-field"). UNAVAILABLE without a kind is gRPC's own (no server answered);
    the runtime's RESOURCE_EXHAUSTED for too many concurrent calls means busy, not too large."""
    if "bodyfit-kind" not in trailing:
        if code == "UNAVAILABLE":
            sent = not any(words in details.lower() for words in _NOT_SENT)
            message = f"cannot reach the bodyfit gRPC server: {details}"
            return ConnectionFailedError(message, code, retry_after=retry_after, sent=sent)
        if code == "RESOURCE_EXHAUSTED" and "concurrent rpc limit" in details.lower():
            return ServerBusyError(details, code, retry_after=retry_after)
    kind = str(trailing.get("bodyfit-kind") or GRPC_STATUS_KINDS.get(code, "internal"))
    field = trailing.get("bodyfit-field")
    return ERRORS.get(kind, ServerError)(
        details, code, None if field is None else str(field), retry_after=retry_after
    )


def error_from_validation(exc: ValidationError, what: str) -> ServerError:
    """The error of an answer that does not match the wire contract (:mod:`bodyfit.wire`): ``what`` the
    answer was, and where it differs (the first few keys at fault, as ``arrays.vertices: Field
    required``)."""
    errors = exc.errors(include_url=False)
    places = [f"{'.'.join(str(p) for p in e['loc']) or 'the document'}: {e['msg']}" for e in errors[:3]]
    more = f"; {len(errors) - 3} more" if len(errors) > 3 else ""
    return ServerError(
        f"the server's {what} does not match this SDK's wire models ({'; '.join(places)}{more}); is the "
        "server a different bodyfit version?"
    )

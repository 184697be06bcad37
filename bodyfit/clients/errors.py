"""Typed exceptions the SDK raises, built from the server's error body (REST problem+json or a gRPC
status). ``kind`` is the wire name shared by both transports: invalid_argument, resource_exhausted,
unavailable, deadline_exceeded, cancelled, not_found, internal."""

from __future__ import annotations

from typing import Any


class BodyfitClientError(Exception):
    """Base class. ``status``: the HTTP status (or the gRPC code's name); ``detail``: what was wrong and
    how to fix it; ``field``: the request field at fault, when known; ``retryable``: safe to send again."""

    kind = "internal"
    retryable = False

    def __init__(self, detail: str, status: int | str | None = None, field: str | None = None) -> None:
        super().__init__(detail if field is None else f"{field}: {detail}")
        self.detail = detail
        self.status = status
        self.field = field


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


def error_from_problem(problem: dict[str, Any], status: int | str | None) -> BodyfitClientError:
    """The typed exception for a problem document ``{"kind", "detail", "field", ...}``."""
    cls = ERRORS.get(str(problem.get("kind", "")), ServerError)
    detail = str(problem.get("detail") or problem.get("title") or "the server gave no detail")
    field = problem.get("field")
    return cls(detail, status, None if field is None else str(field))

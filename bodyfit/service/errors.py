"""Domain errors of the service core. Transports map ``kind`` to a status (REST: problem+json with an HTTP
status; gRPC: a status code); the message always says what was wrong and how to fix it."""

from __future__ import annotations

from typing import ClassVar

from bodyfit.models.errors import AssetError, BodyfitError


class ServiceError(Exception):
    """Base of every error the core raises on purpose.

    Args:
        detail: what was wrong and how to fix it (shown to the client as is).
        field: the request field at fault, when there is one.
    """

    kind: ClassVar[str] = "internal"
    title: ClassVar[str] = "Internal error"

    def __init__(self, detail: str, field: str | None = None) -> None:
        super().__init__(detail if field is None else f"{field}: {detail}")
        self.detail = detail
        self.field = field


class InvalidInputError(ServiceError):
    """The request is malformed or its values are out of range (REST 422 / 400, gRPC INVALID_ARGUMENT)."""

    kind = "invalid_argument"
    title = "Invalid input"


class LimitExceededError(ServiceError):
    """The request is larger than the server's configured limits (REST 413, gRPC RESOURCE_EXHAUSTED)."""

    kind = "resource_exhausted"
    title = "Request too large"


class BusyError(ServiceError):
    """Every worker slot is taken; safe to retry later (REST 503, gRPC RESOURCE_EXHAUSTED)."""

    kind = "unavailable"
    title = "Server busy"


class DeadlineExceededError(ServiceError):
    """The work ran past its time limit (REST 504, gRPC DEADLINE_EXCEEDED)."""

    kind = "deadline_exceeded"
    title = "Time limit exceeded"


class JobCancelledError(ServiceError):
    """The client went away or cancelled; the work stopped (REST 499, gRPC CANCELLED)."""

    kind = "cancelled"
    title = "Cancelled"


def as_service_error(exc: BaseException) -> ServiceError | None:
    """``exc`` as the error a transport reports: itself for a :class:`ServiceError`, an
    :class:`InvalidInputError` for the model layer's input errors (:class:`BodyfitError`: a bad scan, frames
    or sequence found in the middle of the work), None for anything else (a bug: an internal error). A
    missing or corrupted asset (:class:`AssetError`) is the server's fault, never the client's: None."""
    if isinstance(exc, ServiceError):
        return exc
    if isinstance(exc, BodyfitError) and not isinstance(exc, AssetError):
        return InvalidInputError(str(exc))
    return None

"""Python SDK and command-line interface. Depends on the wire contract only, not on the server code.

``Client`` / ``AsyncClient`` talk REST (httpx); ``bodyfit.clients.grpc_client.GrpcClient`` talks gRPC (needs
grpcio). Errors are the typed exceptions of :mod:`bodyfit.clients.errors`. All four clients (REST and
gRPC, sync and async) are thin transports over :mod:`bodyfit.clients.core`: the same methods, checks,
results, errors and :class:`RetryPolicy`.
"""

from bodyfit.clients.core import RetryPolicy
from bodyfit.clients.errors import (
    BodyfitClientError,
    ConnectionFailedError,
    InvalidRequestError,
    NotFoundError,
    RequestCancelledError,
    RequestTimeoutError,
    RequestTooLargeError,
    ServerBusyError,
    ServerError,
)
from bodyfit.clients.rest_client import AsyncClient, Client

__all__ = [
    "AsyncClient",
    "BodyfitClientError",
    "Client",
    "ConnectionFailedError",
    "InvalidRequestError",
    "NotFoundError",
    "RequestCancelledError",
    "RequestTimeoutError",
    "RequestTooLargeError",
    "RetryPolicy",
    "ServerBusyError",
    "ServerError",
]

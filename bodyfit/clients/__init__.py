"""Python SDK and command-line interface. Depends on the wire contract only, not on the server code.

``Client`` / ``AsyncClient`` talk REST (httpx); ``bodyfit.clients.grpc_client.GrpcClient`` talks gRPC (needs
grpcio). Errors are the typed exceptions of :mod:`bodyfit.clients.errors`.
"""

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
    "ServerBusyError",
    "ServerError",
]

"""The SDK's one request core under four thin transports (REST and gRPC, each sync and async).

- :mod:`.operations`: the operations, their arguments checked once, and events folded into results;
- :mod:`.retry`: the retry policy (full-jitter backoff, ``Retry-After``, a time budget, safe cases only);
- :mod:`.base`: the public methods, declared once, and the call loop; a transport implements ``_send``.

Typed errors are built from the server's problem document or gRPC status by
:mod:`bodyfit.clients.errors`.
"""

from bodyfit.clients.core.base import AsyncClientCore, SyncClientCore
from bodyfit.clients.core.operations import Event, Operation
from bodyfit.clients.core.retry import RetryPolicy, parse_retry_after, safe_to_retry

__all__ = [
    "AsyncClientCore",
    "Event",
    "Operation",
    "RetryPolicy",
    "SyncClientCore",
    "parse_retry_after",
    "safe_to_retry",
]

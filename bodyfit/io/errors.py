"""The two errors every reader of :mod:`bodyfit.io` raises. Both are :class:`BodyfitError`\\ s, so a caller
that maps the model layer's errors to "invalid input" is safe by default; the service maps
:class:`FileLimitError` to "too large" (REST 413, gRPC RESOURCE_EXHAUSTED) before that."""

from __future__ import annotations

from bodyfit.models.errors import BodyfitError


class FileFormatError(BodyfitError):
    """A file is not in its format, is truncated or corrupt, or holds arrays of the wrong type or shape
    (REST 422, gRPC INVALID_ARGUMENT).

    Args:
        message: what was wrong and how to fix it.
        key: the array (or header field) at fault, when there is one.
    """

    def __init__(self, message: str, key: str | None = None) -> None:
        super().__init__(message)
        self.key = key


class FileLimitError(BodyfitError):
    """A file declares more than a configured limit: decompressed bytes, points, faces or frames (REST 413,
    gRPC RESOURCE_EXHAUSTED). Raised from the headers, before the data is decompressed or allocated.

    Args:
        message: the declared size, the limit and how to get under it.
        key: the array (or header field) at fault, when there is one.
    """

    def __init__(self, message: str, key: str | None = None) -> None:
        super().__init__(message)
        self.key = key

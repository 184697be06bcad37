"""File formats read or written by bodyfit, every one header-validated before any array is built.

Pure numpy: no torch, no web or gRPC imports, so the readers serve the service, the command line and the
client alike. Errors: :class:`FileFormatError` (malformed) and :class:`FileLimitError` (over a limit).
"""

from bodyfit.io.errors import FileFormatError, FileLimitError
from bodyfit.io.npz import DEFAULT_MAX_BYTES, ArraySpec, Dim, npz_keys, read_npz

__all__ = [
    "DEFAULT_MAX_BYTES",
    "ArraySpec",
    "Dim",
    "FileFormatError",
    "FileLimitError",
    "npz_keys",
    "read_npz",
]

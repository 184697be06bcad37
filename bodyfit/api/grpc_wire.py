"""Arrays on the gRPC wire (``bodyfit.v1.Array``: dtype, shape, little-endian C-order bytes), shared by
the server and the gRPC client: both sides of the contract, numpy only."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from bodyfit.api import bodyfit_pb2 as pb

DTYPES = ("float32", "float64", "int32", "int64", "bool")
FLOATS = ("float32", "float64")
"""The dtypes of real-valued inputs (parameters, frames): the server refuses int and bool arrays for them,
as the service core does for every transport."""
MAX_NDIM = 8
MAX_DIMENSION = (1 << 31) - 1
"""Largest declared dimension: no gRPC message holds more elements (an empty array may declare any size,
so a size is checked against this as well as against the data's length)."""
STATUS_KINDS = {
    "INVALID_ARGUMENT": "invalid_argument",
    "RESOURCE_EXHAUSTED": "resource_exhausted",
    "UNAVAILABLE": "unavailable",
    "DEADLINE_EXCEEDED": "deadline_exceeded",
    "CANCELLED": "cancelled",
    "UNIMPLEMENTED": "not_found",
    "NOT_FOUND": "not_found",
}
"""gRPC status code name -> the error kind shared with REST problem documents."""


class WireError(ValueError):
    """A malformed array; ``field`` names it."""

    def __init__(self, field: str, detail: str) -> None:
        super().__init__(f"{field}: {detail}")
        self.field = field
        self.detail = detail


def to_proto(a: np.ndarray) -> pb.Array:
    """A numpy array as ``Array`` (float16 / uint types are widened to a wire dtype)."""
    arr = np.asarray(a)
    if arr.dtype.name not in DTYPES:
        arr = arr.astype(np.float64 if arr.dtype.kind == "f" else np.int64)
    little = np.ascontiguousarray(arr, dtype=arr.dtype.newbyteorder("<"))
    return pb.Array(dtype=arr.dtype.name, shape=list(arr.shape), data=little.tobytes())


def from_proto(msg: pb.Array, field: str, dtypes: Sequence[str] = DTYPES) -> np.ndarray:
    """The numpy array of ``msg`` (native byte order, a copy); ``dtypes``: those accepted for this field
    (:data:`FLOATS` for real values).

    Raises:
        WireError: a dtype not in ``dtypes``, more than :data:`MAX_NDIM` dimensions, negative sizes or sizes
        above :data:`MAX_DIMENSION`, or a byte count that does not match dtype and shape (all checked before
        any array is built).
    """
    if msg.dtype not in DTYPES:
        raise WireError(field, f"dtype {msg.dtype!r} is not one of {', '.join(DTYPES)}")
    if msg.dtype not in dtypes:
        what = "floats" if tuple(dtypes) == FLOATS else "one of " + ", ".join(dtypes)
        raise WireError(field, f"must hold {what} ({', '.join(dtypes)}); got {msg.dtype}")
    shape = tuple(int(n) for n in msg.shape)
    if len(shape) > MAX_NDIM:
        raise WireError(field, f"shape {shape} has {len(shape)} dimensions; at most {MAX_NDIM} are accepted")
    if any(n < 0 for n in shape):
        raise WireError(field, f"shape {shape} has negative sizes")
    if any(n > MAX_DIMENSION for n in shape):
        raise WireError(
            field, f"shape {shape} declares a size above {MAX_DIMENSION:,}; no message holds that many values"
        )
    dtype = np.dtype(msg.dtype).newbyteorder("<")
    expected = math.prod(shape) * dtype.itemsize  # Python integers: no overflow
    if len(msg.data) != expected:
        raise WireError(
            field, f"holds {len(msg.data)} bytes but dtype {msg.dtype} and shape {shape} need {expected}"
        )
    return np.frombuffer(msg.data, dtype=dtype).reshape(shape).astype(dtype.newbyteorder("="))


def optional(parent: Any, field: str, dtypes: Sequence[str] = DTYPES) -> np.ndarray | None:
    """The array in message field ``field`` of ``parent`` (:func:`from_proto`), or None when the field was
    not set."""
    return from_proto(getattr(parent, field), field, dtypes) if parent.HasField(field) else None

"""Arrays on the JSON wire: ``{"dtype", "shape", "data"}`` with ``data`` the base64 of the little-endian
C-order bytes, so that clients get exact values without parsing long lists of numbers. The gRPC wire's
``bodyfit.v1.Array`` has the same three fields, with ``data`` as raw bytes; :class:`WireArray` reads both."""

from __future__ import annotations

import base64
import binascii
import math
from typing import Annotated, Literal

import numpy as np
from pydantic import BeforeValidator, Field, PlainSerializer, WithJsonSchema, model_validator

from bodyfit.wire.base import WireModel

DTYPES = ("float32", "float64", "int32", "int64", "bool")
"""The dtypes on the wire; others are widened by :meth:`WireArray.from_numpy`."""
MAX_NDIM = 8
Dtype = Literal["float32", "float64", "int32", "int64", "bool"]


def _from_base64(value: object) -> object:
    """Text is base64 (the JSON wire); bytes are taken as they are (the gRPC wire's raw ``data``)."""
    if isinstance(value, str):
        try:
            return base64.b64decode(value, validate=True)
        except binascii.Error as exc:
            raise ValueError(f"not base64 text ({exc})") from None
    return value


def _to_base64(data: bytes) -> str:
    return base64.b64encode(data).decode()


Base64Bytes = Annotated[
    bytes,
    BeforeValidator(_from_base64),
    PlainSerializer(_to_base64, return_type=str, when_used="json"),
    WithJsonSchema({"type": "string", "contentEncoding": "base64"}),
]
"""Bytes that travel as base64 text in JSON (standard alphabet, padded, no line breaks)."""


class WireArray(WireModel):
    """One numpy array: ``dtype`` (one of :data:`DTYPES`), ``shape`` (at most :data:`MAX_NDIM` sizes) and
    ``data``, the little-endian C-order bytes (base64 in JSON). The byte count is checked against dtype and
    shape when the document is read, before any array is built."""

    dtype: Dtype
    shape: Annotated[tuple[Annotated[int, Field(ge=0)], ...], Field(max_length=MAX_NDIM)]
    data: Base64Bytes = Field(description="base64 of the little-endian C-order bytes")

    @model_validator(mode="after")
    def _sized(self) -> WireArray:
        need = math.prod(self.shape) * np.dtype(self.dtype).itemsize  # Python integers: no overflow
        if len(self.data) != need:
            raise ValueError(
                f"data holds {len(self.data)} bytes but dtype {self.dtype} and shape {list(self.shape)} need "
                f"{need}"
            )
        return self

    @classmethod
    def from_numpy(cls, a: np.ndarray) -> WireArray:
        """``a`` on the wire; float16 and unsigned or narrow integers are widened to float64 / int64."""
        arr = np.asarray(a)
        if arr.dtype.name not in DTYPES:
            arr = arr.astype(np.float64 if arr.dtype.kind == "f" else np.int64)
        little = np.ascontiguousarray(arr, dtype=arr.dtype.newbyteorder("<"))
        return cls(dtype=arr.dtype.name, shape=arr.shape, data=little.tobytes())  # type: ignore[arg-type]

    def to_numpy(self) -> np.ndarray:
        """The array (native byte order; a writable copy)."""
        little = np.dtype(self.dtype).newbyteorder("<")
        return np.frombuffer(self.data, dtype=little).reshape(self.shape).astype(little.newbyteorder("="))

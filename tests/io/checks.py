"""What the reader tests share: archives built to lie (.npy headers, zip flags), a refusal's type and
words, and a block's peak memory."""

from __future__ import annotations

import io
import struct
import tracemalloc
import zipfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np
import pytest

MB = 2**20


def savez(**arrays: np.ndarray) -> bytes:
    """The bytes of ``numpy.savez(file, **arrays)``."""
    buf = io.BytesIO()
    np.savez(buf, **arrays)  # type: ignore[arg-type]
    return buf.getvalue()


def savez_compressed(**arrays: np.ndarray) -> bytes:
    """The bytes of ``numpy.savez_compressed(file, **arrays)``."""
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)  # type: ignore[arg-type]
    return buf.getvalue()


def npy(
    shape: tuple[int, ...], descr: str = "<f8", data: bytes = b"", fortran: bool = False, v: int = 1
) -> bytes:
    """A .npy file whose header says ``shape`` / ``descr`` whatever ``data`` holds (a header that may lie)."""
    header = repr({"descr": descr, "fortran_order": fortran, "shape": shape}).encode("latin1")
    magic, length = b"\x93NUMPY" + bytes([v, 0]), "<H" if v == 1 else "<I"
    header += b" " * (-(len(magic) + struct.calcsize(length) + len(header) + 1) % 64) + b"\n"
    return magic + struct.pack(length, len(header)) + header + data


def archive(members: dict[str, bytes], method: int = zipfile.ZIP_DEFLATED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", method) as zf:
        for name, data in members.items():
            zf.writestr(f"{name}.npy", data)
    return buf.getvalue()


def patch_members(data: bytes, flag: int | None = None, method: int | None = None) -> bytes:
    """Set the general-purpose flag bits / compression method of every member, in both the local headers
    and the central directory (where zipfile reads them)."""
    out = bytearray(data)
    for signature, flag_at, method_at in ((b"PK\x03\x04", 6, 8), (b"PK\x01\x02", 8, 10)):
        at = out.find(signature)
        while at >= 0:
            if flag is not None:
                out[at + flag_at : at + flag_at + 2] = struct.pack("<H", flag)
            if method is not None:
                out[at + method_at : at + method_at + 2] = struct.pack("<H", method)
            at = out.find(signature, at + 4)
    return bytes(out)


@contextmanager
def peak_memory(limit_mb: float) -> Iterator[None]:
    """Assert the block's peak Python / numpy allocation stays under ``limit_mb``."""
    tracemalloc.start()
    try:
        yield
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert peak < limit_mb * MB, f"peak {peak / MB:.1f} MiB"


def refused(error: type[Exception], words: str, call: Callable[[], object], key: str | None = None) -> str:
    with pytest.raises(error) as err:
        call()
    message = str(err.value)
    assert words in message, message
    if key is not None:
        assert getattr(err.value, "key", None) == key
    return message

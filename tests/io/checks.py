"""Assertions shared by the reader tests: a refusal's type and words, and a block's peak memory."""

from __future__ import annotations

import tracemalloc
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import pytest

MB = 2**20


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

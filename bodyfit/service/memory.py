"""Giving memory back to the system after large requests (glibc's allocator; a no-op elsewhere).

A long-lived server that answers one large request (a 256-body glb with skeletons, a long sequence)
otherwise keeps its peak memory: glibc keeps freed heap pages in its arenas, one arena per thread that
ever allocated, and raises its mmap threshold after large frees so that later large arrays land in those
arenas too. :func:`configure_allocator` caps the arenas and pins the threshold once at start-up, and
:class:`MemoryTrimmer` returns freed pages (``malloc_trim``) whenever resident memory has grown.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import threading

LOG = logging.getLogger("bodyfit.service")
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -3, -8


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        libc = ctypes.CDLL(name)
        _ = libc.malloc_trim, libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl, macOS)
        return None
    return libc


def configure_allocator(arenas: int = 2, mmap_threshold: int = 1 << 20) -> bool:
    """Cap glibc's arenas at ``arenas`` and serve every allocation of ``mmap_threshold`` bytes or more with
    its own mapping (returned to the system when freed). Call once, at start-up, before worker threads
    allocate. Returns whether the allocator took the settings (False where it is not glibc)."""
    libc = _libc()
    if libc is None:
        return False
    done = libc.mallopt(_M_ARENA_MAX, arenas) == 1
    done &= libc.mallopt(_M_MMAP_THRESHOLD, mmap_threshold) == 1
    done &= libc.mallopt(_M_TRIM_THRESHOLD, 2 * mmap_threshold) == 1
    return bool(done)


def resident_bytes() -> int:
    """This process's resident memory (bytes), from /proc; 0 where /proc is missing."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


def trim() -> None:
    """Return the allocator's free pages to the system now (glibc's ``malloc_trim(0)``)."""
    libc = _libc()
    if libc is not None:
        libc.malloc_trim(0)


class MemoryTrimmer:
    """A background thread that trims the heap (:func:`trim`) when resident memory has grown by more than
    ``growth_bytes`` since the last trim, checking every ``interval_s`` seconds (:meth:`start`,
    :meth:`stop`)."""

    def __init__(self, interval_s: float = 1.0, growth_bytes: int = 64 << 20) -> None:
        self.interval_s = interval_s
        self.growth_bytes = growth_bytes
        self.trims = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bodyfit-trim", daemon=True)

    def start(self) -> MemoryTrimmer:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)

    def _run(self) -> None:
        floor = resident_bytes()
        while not self._stop.wait(self.interval_s):
            now = resident_bytes()
            if now - floor > self.growth_bytes:
                trim()
                self.trims += 1
                after = resident_bytes()
                LOG.debug("trimmed the heap: %.0f -> %.0f MB", now / 2**20, after / 2**20)
                floor = after
            else:
                floor = min(floor, now)

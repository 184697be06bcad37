"""Deprecated: moved to :mod:`bodyfit.io.scans`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.io.scans import (
    FACES_PER_POINT,
    FORMATS,
    MAX_EXTENT_M,
    MIN_EXTENT_M,
    MIN_EXTENT_MM,
    MIN_POINTS,
    Scan,
    ScanError,
    largest_extent,
    load_scan,
    sample_surface,
    save_scan,
    scan_from_arrays,
)

__all__ = [
    "FACES_PER_POINT",
    "FORMATS",
    "MAX_EXTENT_M",
    "MIN_EXTENT_M",
    "MIN_EXTENT_MM",
    "MIN_POINTS",
    "Scan",
    "ScanError",
    "largest_extent",
    "load_scan",
    "sample_surface",
    "save_scan",
    "scan_from_arrays",
]

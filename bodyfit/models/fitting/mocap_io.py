"""Deprecated: moved to :mod:`bodyfit.io.mocap`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.io.mocap import (
    UNITS,
    MarkerTrial,
    MocapFormatError,
    check_rotation,
    lab_rotation,
    parse_c3d,
    parse_trc,
    read_c3d,
    read_markers,
    read_trc,
    write_trc,
)

__all__ = [
    "UNITS",
    "MarkerTrial",
    "MocapFormatError",
    "check_rotation",
    "lab_rotation",
    "parse_c3d",
    "parse_trc",
    "read_c3d",
    "read_markers",
    "read_trc",
    "write_trc",
]

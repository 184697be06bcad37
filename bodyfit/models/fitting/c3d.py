"""Deprecated: moved to :mod:`bodyfit.io.c3d`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.io.c3d import (
    BLOCK,
    C3DError,
    parse_c3d_points,
    parse_parameters,
)

__all__ = [
    "BLOCK",
    "C3DError",
    "parse_c3d_points",
    "parse_parameters",
]

"""Deprecated: moved to :mod:`bodyfit.io.bvh`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.io.bvh import (
    CHANNELS,
    CMU_UNITS,
    BvhJoint,
    BvhMotion,
    parse_bvh,
    read_bvh,
)

__all__ = [
    "CHANNELS",
    "CMU_UNITS",
    "BvhJoint",
    "BvhMotion",
    "parse_bvh",
    "read_bvh",
]

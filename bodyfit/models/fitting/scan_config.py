"""Deprecated: moved to :mod:`bodyfit.models.fitting.scan.config`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.models.fitting.scan.config import (
    DEFAULT_BRANCHES,
    DEFAULT_PHASES,
    FLIPPED_MARGIN,
    PART_NAMES,
    PARTIAL_EXTENT_M,
    UPPER_BODY_PHASES,
    ScanBranch,
    ScanFitConfig,
    ScanPhase,
)

__all__ = [
    "DEFAULT_BRANCHES",
    "DEFAULT_PHASES",
    "FLIPPED_MARGIN",
    "PARTIAL_EXTENT_M",
    "PART_NAMES",
    "UPPER_BODY_PHASES",
    "ScanBranch",
    "ScanFitConfig",
    "ScanPhase",
]

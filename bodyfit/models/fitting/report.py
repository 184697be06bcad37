"""Deprecated: moved to :mod:`bodyfit.models.fitting.common.report`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.models.fitting.common.report import (
    DistanceStats,
    FitReport,
    count_limit_violations,
)

__all__ = [
    "DistanceStats",
    "FitReport",
    "count_limit_violations",
]

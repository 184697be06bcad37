"""Deprecated: moved to :mod:`bodyfit.models.fitting.scan.fitter`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.models.fitting.scan.fitter import (
    CONFIDENT_MEAN_MM,
    COVERED_MM,
    DISTAL_SEARCH,
    DISTAL_TRUNCATION_M,
    DISTAL_VERTICES,
    EXPLAINED_M,
    INLIER_MM,
    MIN_COVERAGE,
    MIN_INLIER_FRACTION,
    REACH_MM,
    STRAIGHTENED,
    UNSUPPORTED,
    VISIBLE_COS,
    Progress,
    ScanFit,
    ScanFitter,
    clean_points,
    orientation_candidates,
)

__all__ = [
    "CONFIDENT_MEAN_MM",
    "COVERED_MM",
    "DISTAL_SEARCH",
    "DISTAL_TRUNCATION_M",
    "DISTAL_VERTICES",
    "EXPLAINED_M",
    "INLIER_MM",
    "MIN_COVERAGE",
    "MIN_INLIER_FRACTION",
    "REACH_MM",
    "STRAIGHTENED",
    "UNSUPPORTED",
    "VISIBLE_COS",
    "Progress",
    "ScanFit",
    "ScanFitter",
    "clean_points",
    "orientation_candidates",
]

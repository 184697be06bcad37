"""Deprecated: moved to :mod:`bodyfit.models.fitting.mocap.marker_ik`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.models.fitting.mocap.marker_ik import (
    ARC_SMALL,
    MarkerChain,
    ResidualFn,
    SolveResult,
    fill_gaps,
    levenberg_marquardt,
    marker_jacobian,
    marker_positions,
    table_with_slope,
)

__all__ = [
    "ARC_SMALL",
    "MarkerChain",
    "ResidualFn",
    "SolveResult",
    "fill_gaps",
    "levenberg_marquardt",
    "marker_jacobian",
    "marker_positions",
    "table_with_slope",
]

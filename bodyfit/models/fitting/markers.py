"""Deprecated: moved to :mod:`bodyfit.models.fitting.mocap.fitter`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.models.fitting.mocap.fitter import (
    CALIBRATION_FRAMES,
    MAX_MEAN_ERROR,
    MIN_VISIBLE,
    MarkerFit,
    fit_markers,
    observed_positions,
)

__all__ = [
    "CALIBRATION_FRAMES",
    "MAX_MEAN_ERROR",
    "MIN_VISIBLE",
    "MarkerFit",
    "fit_markers",
    "observed_positions",
]

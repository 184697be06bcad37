"""Deprecated: moved to :mod:`bodyfit.models.fitting.mocap.subject`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.models.fitting.mocap.subject import (
    PLACE_SIGMA,
    Calibration,
    calibrate,
)

__all__ = [
    "PLACE_SIGMA",
    "Calibration",
    "calibrate",
]

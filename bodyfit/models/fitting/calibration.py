"""Deprecated: moved to :mod:`bodyfit.models.fitting.mocap.calibration`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.models.fitting.mocap.calibration import (
    MARKER_SIGMA,
    RANGE_MARGIN,
    SCALE_SIGMA,
    SOFT_SIGMA,
    DofPlan,
    ScaleModel,
    VirtualMarkers,
    moved_bodies,
    pelvis_start,
    place_markers,
    virtual_markers,
)

__all__ = [
    "MARKER_SIGMA",
    "RANGE_MARGIN",
    "SCALE_SIGMA",
    "SOFT_SIGMA",
    "DofPlan",
    "ScaleModel",
    "VirtualMarkers",
    "moved_bodies",
    "pelvis_start",
    "place_markers",
    "virtual_markers",
]

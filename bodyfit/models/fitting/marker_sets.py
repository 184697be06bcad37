"""Deprecated: moved to :mod:`bodyfit.models.fitting.mocap.marker_sets`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.models.fitting.mocap.marker_sets import (
    GAIT2392,
    HALLUX_NAIL,
    MARKER_SETS,
    RAJAGOPAL,
    RAJAGOPAL_MARKERS,
    SKIN_OFFSET,
    MarkerDef,
    MarkerSetDef,
    MarkerSetError,
    Row,
    choose_marker_set,
    normalise_name,
)

__all__ = [
    "GAIT2392",
    "HALLUX_NAIL",
    "MARKER_SETS",
    "RAJAGOPAL",
    "RAJAGOPAL_MARKERS",
    "SKIN_OFFSET",
    "MarkerDef",
    "MarkerSetDef",
    "MarkerSetError",
    "Row",
    "choose_marker_set",
    "normalise_name",
]

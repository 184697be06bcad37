"""Deprecated: moved to :mod:`bodyfit.cli.fit.markers`; this path will be removed in the next release. Its
public names are re-exported from there."""

from bodyfit.cli.fit.markers import (
    MARKER_SUFFIXES,
    MarkerOptions,
    fit_marker_trials,
    is_marker_file,
    parse_static_pose,
)

__all__ = ["MARKER_SUFFIXES", "MarkerOptions", "fit_marker_trials", "is_marker_file", "parse_static_pose"]

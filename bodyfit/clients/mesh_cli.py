"""Deprecated: moved to :mod:`bodyfit.cli.fit.scan`; this path will be removed in the next release. Its
public names are re-exported from there."""

from bodyfit.cli.fit.scan import HELPER_SCANS, fit_mesh_files

__all__ = ["HELPER_SCANS", "fit_mesh_files"]

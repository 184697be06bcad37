"""Deprecated: moved to :mod:`bodyfit.models.fitting.scan.view`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.models.fitting.scan.view import (
    Silhouette,
    ViewConfig,
    depth_bulge,
    layered_fraction,
    view_direction,
)

__all__ = [
    "Silhouette",
    "ViewConfig",
    "depth_bulge",
    "layered_fraction",
    "view_direction",
]

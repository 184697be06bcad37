"""Deprecated: moved to :mod:`bodyfit.models.fitting.common.nearest`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.models.fitting.common.nearest import (
    PointTree,
)

__all__ = [
    "PointTree",
]

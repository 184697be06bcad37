"""Deprecated: moved to :mod:`bodyfit.models.fitting.sequence.offsets`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.models.fitting.sequence.offsets import (
    OffsetConfig,
    fit_rest_offsets,
)

__all__ = [
    "OffsetConfig",
    "fit_rest_offsets",
]

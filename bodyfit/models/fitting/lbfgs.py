"""Deprecated: moved to :mod:`bodyfit.models.fitting.common.lbfgs`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.models.fitting.common.lbfgs import (
    ARMIJO,
    BACKTRACK,
    CURVATURE_EPS,
    LbfgsResult,
    batched_lbfgs,
)

__all__ = [
    "ARMIJO",
    "BACKTRACK",
    "CURVATURE_EPS",
    "LbfgsResult",
    "batched_lbfgs",
]

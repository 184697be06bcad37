"""Deprecated: moved to :mod:`bodyfit.models.fitting.common.nonrigid`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.models.fitting.common.nonrigid import (
    NonRigidConfig,
    geman_mcclure_weights,
    refine_nonrigid,
    solve_offsets,
)

__all__ = [
    "NonRigidConfig",
    "geman_mcclure_weights",
    "refine_nonrigid",
    "solve_offsets",
]

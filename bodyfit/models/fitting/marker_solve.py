"""Deprecated: moved to :mod:`bodyfit.models.fitting.mocap.marker_solve`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.models.fitting.mocap.marker_solve import (
    COARSE_STRIDE,
    DISTAL_ROOTS,
    IKSolution,
    MarkerProblem,
    distal_bodies,
    distal_dofs,
    marker_errors,
    solve_ik,
)

__all__ = [
    "COARSE_STRIDE",
    "DISTAL_ROOTS",
    "IKSolution",
    "MarkerProblem",
    "distal_bodies",
    "distal_dofs",
    "marker_errors",
    "solve_ik",
]

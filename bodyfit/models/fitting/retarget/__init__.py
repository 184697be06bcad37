"""Retargeting skeletal motion (BVH joint rotations) onto our skeleton: :mod:`.fitter`.

Deprecated: the module ``bodyfit.models.fitting.retarget`` moved to
:mod:`bodyfit.models.fitting.retarget.fitter`;
this path will be removed in the next release as a module path (the names re-exported here from
:mod:`bodyfit.models.fitting.retarget.fitter` go; the package stays).
"""

from bodyfit.models.fitting.retarget.fitter import (
    CMU_MAP,
    PRIOR,
    ROTATION_WEIGHT,
    TEMPORAL_PULL,
    TEMPORAL_WINDOW,
    U_MAX,
    Retargeted,
    Segment,
    SegmentMap,
    retarget,
    unwrap_pelvis,
    wrap_pelvis,
)

__all__ = [
    "CMU_MAP",
    "PRIOR",
    "ROTATION_WEIGHT",
    "TEMPORAL_PULL",
    "TEMPORAL_WINDOW",
    "U_MAX",
    "Retargeted",
    "Segment",
    "SegmentMap",
    "retarget",
    "unwrap_pelvis",
    "wrap_pelvis",
]

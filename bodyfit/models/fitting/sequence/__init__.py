"""Fitting sequences of registered meshes or BVH motion, with rest-pose offsets for the person's detail
(:mod:`.offsets`): the fitter's pipeline is in :mod:`.fitter`, its settings in :mod:`.config`, the frames of
reference and per-frame arrays in :mod:`.frames`, the pose fits in :mod:`.poses`, the sequence-level numbers
in :mod:`.stats` and the results in :mod:`.result`.

Deprecated: the module ``bodyfit.models.fitting.sequence`` moved to
:mod:`bodyfit.models.fitting.sequence.fitter`;
this path will be removed in the next release as a module path (the names re-exported here from
:mod:`bodyfit.models.fitting.sequence.fitter` go; the package stays).
"""

from bodyfit.models.fitting.sequence.fitter import (
    FRAME_STAGES,
    KEY_STAGES,
    PELVIS_WEIGHT,
    FrameSource,
    JitterSum,
    SequenceConfig,
    SequenceFit,
    SequenceFitter,
    SequenceFrames,
    SequenceStats,
    fit_sequence,
    jitter,
)

__all__ = [
    "FRAME_STAGES",
    "KEY_STAGES",
    "PELVIS_WEIGHT",
    "FrameSource",
    "JitterSum",
    "SequenceConfig",
    "SequenceFit",
    "SequenceFitter",
    "SequenceFrames",
    "SequenceStats",
    "fit_sequence",
    "jitter",
]

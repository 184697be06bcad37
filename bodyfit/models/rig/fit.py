"""Fitting meshes of a known person with their rig: the subject's shape and template offsets are fixed, only
the poses are fitted (:class:`RegisteredFitter` with pose-only stages)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.registered.fitter import BodyFit, RegisteredFitter
from bodyfit.models.fitting.registered.stages import DEFAULT_STAGES, RegisteredFitConfig
from bodyfit.models.rig.subject import Subject

POSE_STAGES = tuple(replace(stage, shape="none") for stage in DEFAULT_STAGES)
"""The registered fitter's stages with the shape frozen."""


def subject_fitter(model: BodyModel, subject: Subject) -> RegisteredFitter:
    """A registered-mesh fitter for ``subject``: its template offsets and pose-only stages.

    Raises:
        SubjectError: the subject was built for another body model.
    """
    subject.check_model(model)
    return RegisteredFitter(model, RegisteredFitConfig(stages=POSE_STAGES)).with_offsets(subject.offsets)


def fit_registered(
    model: BodyModel, subject: Subject, targets: np.ndarray, weights: np.ndarray | None = None
) -> BodyFit:
    """Poses of ``subject`` fitted to B meshes (B, V, 3) metres in our topology, any placement, with
    per-vertex weights (B, V); the shape stays the subject's."""
    fitter = subject_fitter(model, subject)
    x, w = fitter.validate(targets, weights)
    q0, r0 = fitter.bone_start(x, w)
    shape = np.tile(subject.shape, (len(x), 1))
    return fitter.fit(x, w, init=BodyFit(shape, q0, r0, x, x))

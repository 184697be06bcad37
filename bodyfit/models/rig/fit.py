"""Fitting meshes of a known person with their rig: the subject's shape, template offsets, skinning weights
and joints are fixed, only the poses are fitted (:class:`RegisteredFitter` with pose-only stages)."""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np

from bodyfit.models.body.model import BodyDecoder, BodyModel
from bodyfit.models.fitting.registered.fitter import BodyFit, RegisteredFitter
from bodyfit.models.fitting.registered.stages import DEFAULT_STAGES, RegisteredFitConfig
from bodyfit.models.rig.subject import Subject

POSE_STAGES = tuple(replace(stage, shape="none") for stage in DEFAULT_STAGES)
"""The registered fitter's stages with the shape frozen."""


def with_decoder(fitter: RegisteredFitter, decoder: BodyDecoder) -> RegisteredFitter:
    """``fitter`` with one person's decoder (their offsets, weights and joints: :class:`PersonalParts`) on
    every vertex set; its stages, preconditioning and settings are shared."""
    out = copy.copy(fitter)
    out.decoder = decoder
    out.decoders = {k: decoder if k == "all" else decoder.restricted(v) for k, v in fitter.index.items()}
    return out


def subject_fitter(model: BodyModel, subject: Subject) -> RegisteredFitter:
    """A registered-mesh fitter for ``subject``: everything personal in its decoder, pose-only stages.

    Raises:
        SubjectError: the subject was built for another body model.
    """
    fitter = RegisteredFitter(model, RegisteredFitConfig(stages=POSE_STAGES))
    return with_decoder(fitter, subject.decoder(model, fitter.config.dtype))


def fit_registered(
    model: BodyModel, subject: Subject, targets: np.ndarray, weights: np.ndarray | None = None
) -> BodyFit:
    """Poses of ``subject`` fitted to B meshes (B, V, 3) metres in our topology, any placement, with
    per-vertex weights (B, V); the shape stays the subject's.

    Each mesh is fitted by the generic model first (its own shape and pose), and the subject's pose fit
    starts from that pose: a pose-only fit started from the bodies' rigid motions alone stops in local
    minima (arms and spine settled a few degrees off) that the generic fit, free to change the shape on the
    way, avoids."""
    fitter = subject_fitter(model, subject)
    x, w = fitter.validate(targets, weights)
    generic = RegisteredFitter(model).fit(x, w)
    shape = np.tile(subject.shape, (len(x), 1))
    return fitter.fit(x, w, init=BodyFit(shape, generic.coordinates, generic.root, x, x))

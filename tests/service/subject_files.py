"""Small subject files for tests of ``subject=``: a person outside the shape space (a shape plus smooth
rest-pose offsets that no shape coefficients reproduce), built with :class:`Subject` directly."""

from __future__ import annotations

import io

import numpy as np

from bodyfit.models.body.model import BodyModel
from bodyfit.models.rig.subject import Subject, model_fingerprint

WAVE_MM = 12.0
"""Amplitude of the offsets: a horizontal ripple along the body's height, outwards from its axis."""


def ripple_offsets(model: BodyModel, amplitude_mm: float = WAVE_MM) -> np.ndarray:
    """(V, 3) metres: each vertex moved outwards from the body's vertical axis by a sine of its height
    (a period of about 25 cm), a change of surface that the shape space's smooth bases cannot follow."""
    rest = np.asarray(model.data["vertices_mean"], np.float64)
    out = rest - rest.mean(0)
    out[:, 1] = 0.0
    out /= np.linalg.norm(out, axis=1, keepdims=True) + 1e-9
    return (amplitude_mm / 1000.0 * np.sin(rest[:, 1] * 25.0))[:, None] * out


def make_subject(model: BodyModel, seed: int = 0, amplitude_mm: float = WAVE_MM) -> Subject:
    """A subject of ``model``: shape coefficients drawn at 0.6 standard deviations and
    :func:`ripple_offsets`."""
    shape = np.random.default_rng(seed).normal(size=model.n_shape) * 0.6
    n_dof = model.skeleton.n_dof
    offsets = ripple_offsets(model, amplitude_mm)
    return Subject(shape, offsets, model_fingerprint(model), np.zeros((1, n_dof)), np.zeros((1, 3)), ("a",))


def damaged(data: bytes) -> list[tuple[str, bytes]]:
    """Broken versions of a subject file, each with what is wrong: cut short, a byte flipped in the
    middle, not an npz at all, an npz without a subject's arrays, and an empty upload."""
    flipped = bytearray(data)
    flipped[len(data) // 2] ^= 0xFF
    other = io.BytesIO()
    np.savez(other, points=np.zeros((4, 3)))
    return [
        ("truncated", data[: len(data) // 2]),
        ("flipped", bytes(flipped)),
        ("text", b"this is not a subject file"),
        ("other npz", other.getvalue()),
        ("empty", b""),
    ]

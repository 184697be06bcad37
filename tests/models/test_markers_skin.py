"""The skin step of marker fits: identity coefficients from markers a fixed distance outside the skin."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common.surface import vertex_normals
from bodyfit.models.fitting.mocap.skin import (
    MARKER_OFFSET,
    MarkerSkinError,
    bone_coefficients,
    fit_skin,
)

T = 10


@pytest.fixture(scope="module")
def model() -> BodyModel:
    return BodyModel.load()


def _walk(model: BodyModel) -> tuple[np.ndarray, np.ndarray]:
    """A few frames of hip and knee flexion: coordinates (T, n_dof), roots (T, 3)."""
    q = np.zeros((T, model.skeleton.n_dof))
    phase = np.linspace(0.0, 3.0, T)
    for i, name in enumerate(model.dof_names):
        side = np.pi if name.endswith("_l") else 0.0
        if name.startswith("hip_flexion"):
            q[:, i] = 0.4 * np.sin(phase + side)
        if name.startswith("knee_angle"):
            q[:, i] = 0.5 * (1.0 + np.sin(phase + side))
    root = np.zeros((T, 3))
    root[:, 1] = 1.0
    return q, root


def _subject(model: BodyModel, seed: int) -> dict[str, np.ndarray]:
    """A body far from the mean in identity, posed through :func:`_walk`, with 60 skin markers."""
    rng = np.random.default_rng(seed)
    shape = np.zeros(model.n_shape)
    shape[: model.n_bone] = rng.normal(0.0, 1.0, model.n_bone)
    shape[model.n_bone :] = rng.normal(0.0, 1.5, model.n_identity)
    q, root = _walk(model)
    out = model.forward(np.repeat(shape[None], T, 0), q, root, dtype=torch.float64)
    verts = out.vertices.numpy()
    normals = vertex_normals(verts, model.faces)
    idx = rng.choice(model.n_vertices, 60, replace=False)
    markers = verts[:, idx] + MARKER_OFFSET * normals[:, idx]
    return {
        "shape": shape,
        "q": q,
        "root": root,
        "verts": verts,
        "scales": out.scales[0].numpy(),
        "markers": markers,
    }


def _errors_mm(model: BodyModel, subject: dict[str, np.ndarray], markers: np.ndarray) -> tuple[float, float]:
    """Mean per-vertex distance (mm) of the recovered skin and of the mean-identity body to the truth."""
    skin = fit_skin(model, subject["scales"], subject["q"], subject["root"], markers)
    recovered = skin.vertices(model, subject["q"], subject["root"])
    mean_shape = subject["shape"].copy()
    mean_shape[model.n_bone :] = 0.0
    mean = model.forward(np.repeat(mean_shape[None], T, 0), subject["q"], subject["root"]).vertices.numpy()
    truth = subject["verts"]
    return (
        float(np.linalg.norm(recovered - truth, axis=-1).mean() * 1000),
        float(np.linalg.norm(mean - truth, axis=-1).mean() * 1000),
    )


def test_recovers_a_known_body_from_clean_markers(model: BodyModel) -> None:
    subject = _subject(model, 3)
    fitted, mean = _errors_mm(model, subject, subject["markers"])
    assert mean > 4.0  # the identity is far enough from the mean to be measurable
    assert fitted < 0.6 * mean


def test_dropouts_are_skipped(model: BodyModel) -> None:
    subject = _subject(model, 4)
    markers = subject["markers"].copy()
    rng = np.random.default_rng(0)
    markers[rng.random(markers.shape[:2]) < 0.2] = np.nan
    markers[:, :5] = np.nan  # five markers never seen
    fitted, mean = _errors_mm(model, subject, markers)
    assert np.isfinite(fitted)
    assert fitted < 0.7 * mean


def test_the_skeleton_keeps_the_calibrated_scales(model: BodyModel) -> None:
    subject = _subject(model, 5)
    scales = subject["scales"] * np.linspace(0.97, 1.03, subject["scales"].size).reshape(
        subject["scales"].shape
    )
    skin = fit_skin(model, scales, subject["q"], subject["root"], subject["markers"])
    q = torch.as_tensor(subject["q"][:1], dtype=torch.float32)
    out = skin.decoder(model)(torch.as_tensor(skin.shape[None], dtype=torch.float32), q, torch.zeros(1, 3))
    np.testing.assert_allclose(out[3][0].numpy(), scales, rtol=1e-5)
    c_b, _ = bone_coefficients(model, subject["scales"])
    np.testing.assert_allclose(c_b, subject["shape"][: model.n_bone], atol=1e-6)


def test_markers_off_the_skin_are_left_out(model: BodyModel) -> None:
    subject = _subject(model, 6)
    markers = subject["markers"].copy()
    markers[:, :4] += np.array([0.0, 0.0, 1.0])  # mislabelled: a metre from any skin
    skin = fit_skin(model, subject["scales"], subject["q"], subject["root"], markers)
    assert not skin.used[:, :4].any()
    assert skin.used[:, 4:].mean() > 0.8


def test_bad_input(model: BodyModel) -> None:
    subject = _subject(model, 7)
    q, root, scales, markers = subject["q"], subject["root"], subject["scales"], subject["markers"]
    with pytest.raises(MarkerSkinError, match="share T"):
        fit_skin(model, scales, q[:-1], root, markers)
    with pytest.raises(MarkerSkinError, match="scales"):
        fit_skin(model, scales[:-1], q, root, markers)
    with pytest.raises(MarkerSkinError, match="finite"):
        fit_skin(model, scales, np.full_like(q, np.nan), root, markers)
    with pytest.raises(MarkerSkinError, match="fewer than 3"):
        fit_skin(model, scales, q, root, markers + 1.0)
    with pytest.raises(MarkerSkinError, match=r"\(T, M, 3\)"):
        fit_skin(model, scales, q, root, markers[..., :2])


def test_the_spiral_decoder_code_is_recovered(model: BodyModel) -> None:
    """The second identity option: a body of the spiral decoder (code 1.5 SD per component) recovered from
    its markers well below the mean code's error."""
    from bodyfit.models.decoders.asset import SpiralBodyModel, load_asset

    spiral = SpiralBodyModel(model, load_asset())
    rng = np.random.default_rng(8)
    shape = np.concatenate([rng.normal(0.0, 1.0, model.n_bone), rng.normal(0.0, 1.5, spiral.d)])
    q, root = _walk(model)
    out = spiral.forward(np.repeat(shape[None], T, 0), q, root)
    truth = out.vertices.double().numpy()
    idx = rng.choice(model.n_vertices, 60, replace=False)
    markers = truth[:, idx] + MARKER_OFFSET * vertex_normals(truth, model.faces)[:, idx]
    skin = fit_skin(model, out.scales[0].numpy(), q, root, markers, spiral=spiral.asset)
    assert skin.code is not None and skin.rest_offsets is not None
    np.testing.assert_array_equal(skin.shape[model.n_bone :], 0.0)
    mean = shape.copy()
    mean[model.n_bone :] = 0.0
    baseline = spiral.forward(np.repeat(mean[None], T, 0), q, root).vertices.numpy()
    fitted = np.linalg.norm(skin.vertices(model, q, root) - truth, axis=-1).mean()
    assert fitted < 0.6 * np.linalg.norm(baseline - truth, axis=-1).mean()

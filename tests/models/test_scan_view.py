"""Single-view detection for partial scans: one depth camera's view is recognised with the side it was
seen from; full scans are not."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from benchmarks import corrupt
from bodyfit.io.scans import sample_surface
from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.scan.view import Silhouette, view_direction
from tests.conftest import random_pose


@pytest.fixture(scope="module")
def bodies() -> tuple[BodyModel, np.ndarray]:
    model = BodyModel.load()
    q = random_pose(model.skeleton, 3, 21) * 0.3
    rng = np.random.default_rng(2)
    shape = rng.normal(size=(3, model.n_shape)) * 0.5
    with torch.no_grad():
        return model, model.forward(shape, q, dtype=torch.float64).vertices.numpy()


@pytest.mark.parametrize("camera", [(2.5, 0.0, 0.0), (-2.5, 0.3, 0.0), (0.0, 0.2, 2.5), (1.8, 1.0, -1.5)])
def test_a_depth_view_is_found_with_its_side(
    bodies: tuple[BodyModel, np.ndarray], camera: tuple[float, ...]
) -> None:
    model, verts = bodies
    rng = np.random.default_rng(5)
    for v in verts:
        centre = v.mean(0)
        points, _ = corrupt.depth_camera_view(
            v, model.faces, centre + np.array(camera), centre, (240, 320), rng=rng
        )
        moved, T = corrupt.random_rigid(points, rng)
        d = view_direction(moved)
        assert d is not None
        truth = T[:3, :3] @ (np.array(camera) / np.linalg.norm(camera))
        assert float(d @ truth) > np.cos(np.radians(30)), (d, truth)


def test_full_scans_are_not_single_views(bodies: tuple[BodyModel, np.ndarray]) -> None:
    model, verts = bodies
    for k, v in enumerate(verts):
        points, _ = sample_surface(v, model.faces, 100_000, seed=k)
        assert view_direction(corrupt.random_rigid(points, np.random.default_rng(k))[0]) is None


def test_a_views_silhouette_holds_the_whole_body_but_not_beside_it(
    bodies: tuple[BodyModel, np.ndarray],
) -> None:
    """Every vertex of the viewed body, its unseen back included, projects inside the silhouette of the
    camera's points; moved along the line of sight it still does (hidden or in front), moved across it by
    half a metre it lies outside by about that much."""
    model, verts = bodies
    v = verts[0]
    centre = v.mean(0)
    points, _ = corrupt.depth_camera_view(
        v, model.faces, centre + np.array([2.5, 0.0, 0.0]), centre, (240, 320), rng=np.random.default_rng(3)
    )
    d = view_direction(points)
    assert d is not None
    sil = Silhouette.of(points, d)
    inside = sil.distance(v)
    assert np.mean(inside == 0.0) > 0.99 and inside.max() < 0.03
    assert np.mean(sil.distance(v + 0.4 * d) == 0.0) > 0.99
    across = sil.distance(v + 0.5 * sil.axes[0])
    assert np.median(across) > 0.25 and across.max() < 0.55
    assert sil.distance(v[:7][None]).shape == (1, 7)

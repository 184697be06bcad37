"""Synthetic scan corruptions: each one measured, not just run."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.distance import pdist

from benchmarks.corrupt import (
    add_noise,
    add_outliers,
    clothing_offset,
    depth_camera_view,
    random_rigid,
    remove_patches,
)
from bodyfit.io.scans import sample_surface
from bodyfit.models.fitting.common.surface import NormalOperators, vertex_normals


@pytest.fixture(scope="module")
def sphere() -> trimesh.Trimesh:
    """Radius 0.5 m at the origin, 5,120 faces."""
    m = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    return m


@pytest.fixture(scope="module")
def body_points() -> np.ndarray:
    """20,000 points on a 1.7 m capsule (+Y up)."""
    m = trimesh.creation.capsule(height=1.3, radius=0.2, count=[32, 32])
    return sample_surface(m.vertices[:, [0, 2, 1]] + [0, 0.85, 0], m.faces[:, [0, 2, 1]], 20_000, seed=0)[0]


def test_add_noise_has_the_requested_sigma(body_points: np.ndarray) -> None:
    noisy = add_noise(body_points, 0.005, np.random.default_rng(0))
    d = noisy - body_points
    assert abs(d.std() - 0.005) < 0.0005 and abs(d.mean()) < 0.0002
    np.testing.assert_array_equal(noisy, add_noise(body_points, 0.005, np.random.default_rng(0)))


@pytest.mark.parametrize("fraction", [0.1, 0.3])
def test_remove_patches_removes_the_fraction_in_patches(body_points: np.ndarray, fraction: float) -> None:
    kept, keep = remove_patches(body_points, fraction, np.random.default_rng(1), patch_radius=0.1)
    assert abs((~keep).mean() - fraction) < 0.05
    np.testing.assert_array_equal(kept, body_points[keep])
    # holes, not thinning: a removed point is typically far from any kept one (point spacing here ~1 cm)
    gap, _ = cKDTree(kept).query(body_points[~keep])
    spacing, _ = cKDTree(body_points).query(body_points, k=2)
    assert np.median(gap) > 3 * np.median(spacing[:, 1])


def test_add_outliers_count_and_box(body_points: np.ndarray) -> None:
    out, is_out = add_outliers(body_points, 0.05, np.random.default_rng(2), margin=0.3)
    assert is_out.sum() == round(0.05 * len(body_points)) == len(out) - len(body_points)
    lo, hi = body_points.min(axis=0) - 0.3, body_points.max(axis=0) + 0.3
    assert ((out[is_out] >= lo) & (out[is_out] <= hi)).all()
    assert (out[is_out].max(axis=0) - out[is_out].min(axis=0) > 0.9 * (hi - lo)).all()  # fill the box
    np.testing.assert_array_equal(np.sort(out[~is_out], axis=0), np.sort(body_points, axis=0))


def test_depth_camera_sees_the_front_of_a_sphere(sphere: trimesh.Trimesh) -> None:
    eye = np.array([0.0, 0.0, 3.0])
    points, face = depth_camera_view(sphere.vertices, sphere.faces, eye, (0, 0, 0), (120, 160), 40.0)
    to_eye = eye - points
    to_eye /= np.linalg.norm(to_eye, axis=1, keepdims=True)
    assert (np.einsum("ij,ij->i", sphere.face_normals[face], to_eye) > 0).all()  # every hit faces the camera
    radial = points / np.linalg.norm(points, axis=1, keepdims=True)
    assert (np.einsum("ij,ij->i", radial, to_eye) > -0.05).all()
    assert np.abs(np.linalg.norm(points, axis=1) - 0.5).max() < 0.001  # on the (faceted) surface
    # The silhouette is a disc of radius f tan(asin(r / d)) pixels; one point per covered pixel.
    focal = 60 / math.tan(math.radians(20))
    assert abs(len(points) / (math.pi * (focal * math.tan(math.asin(0.5 / 3.0))) ** 2) - 1) < 0.02
    # The visible cap reaches the tangent cone: 90 - asin(r / d) = 80.4 degrees from the view axis, about
    # the near half of the sphere.
    angle = np.degrees(np.arccos(np.clip(radial @ [0, 0, 1.0], -1, 1)))
    assert 78 < angle.max() < 81


def test_depth_camera_occlusion_and_jitter(sphere: trimesh.Trimesh) -> None:
    back = 2.0 * sphere.vertices + [0.0, 0.0, -2.0]  # radius 1 m behind: 11.5 deg wide seen from the eye
    v = np.concatenate([sphere.vertices, back])
    f = np.concatenate([sphere.faces, sphere.faces + len(sphere.vertices)])
    eye = np.array([0.0, 0.0, 3.0])
    points, face = depth_camera_view(v, f, eye, (0, 0, -1.0), (120, 160), 60.0)
    on_back = face >= len(sphere.faces)
    assert 0 < on_back.sum() < (~on_back).sum()  # the back sphere peeks out around the front one
    # no back-sphere point lies inside the front sphere's shadow cone seen from the eye
    ray = (points[on_back] - eye) / np.linalg.norm(points[on_back] - eye, axis=1, keepdims=True)
    assert (np.degrees(np.arccos(ray @ [0, 0, -1.0])) > np.degrees(math.asin(0.5 / 3.0)) - 0.3).all()
    a, _ = depth_camera_view(v, f, eye, (0, 0, -1.0), (120, 160), 60.0, np.random.default_rng(5))
    b, _ = depth_camera_view(v, f, eye, (0, 0, -1.0), (120, 160), 60.0, np.random.default_rng(5))
    np.testing.assert_array_equal(a, b)
    assert abs(len(a) - len(points)) < 0.03 * len(points)


def test_depth_camera_is_fast_on_a_body_sized_mesh() -> None:
    m = trimesh.creation.capsule(height=1.3, radius=0.2, count=[96, 140])
    assert len(m.faces) == 26_880
    v, f = m.vertices[:, [0, 2, 1]] + [0, 0.85, 0], m.faces[:, [0, 2, 1]]
    start = time.perf_counter()
    rng = np.random.default_rng(0)
    points, _ = depth_camera_view(v, f, (1.5, 1.0, 0.5), (0, 0.9, 0), (240, 320), 60.0, rng)
    assert time.perf_counter() - start < 1.0
    assert len(points) > 10_000
    assert (points[:, 0] > -0.05).all()  # the far side of the body is hidden


def test_clothing_offset_is_outward_smooth_and_bounded() -> None:
    m = trimesh.creation.capsule(height=1.3, radius=0.2, count=[32, 32])
    v, f = m.vertices[:, [0, 2, 1]] + [0, 0.85, 0], m.faces[:, [0, 2, 1]]
    moved, offset = clothing_offset(v, f, np.random.default_rng(3), max_offset=0.03)
    normals = vertex_normals(v, f)
    along = np.einsum("ij,ij->i", moved - v, normals)
    np.testing.assert_allclose(along, offset, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(moved - v, axis=1), offset, atol=1e-12)
    assert offset.min() >= 0 and abs(offset.max() - 0.03) < 1e-12
    edges = m.edges_unique  # smooth: a gentle slope along every edge (0.03 m over ~0.2 m)
    a, b = edges[:, 0], edges[:, 1]
    slope = np.abs(offset[a] - offset[b]) / np.linalg.norm(v[a] - v[b], axis=1)
    assert slope.max() < 0.3
    assert trimesh.Trimesh(moved, f).volume > trimesh.Trimesh(v, f).volume  # outward, not inward
    reference = trimesh.Trimesh(v, f, process=False).vertex_normals  # angle-weighted; ours area-weighted
    assert np.einsum("ij,ij->i", normals, reference).min() > 0.99
    # float32 vertices (a fitting loop's, in mm) give float32 normals, equal to float32 rounding
    single = vertex_normals((v * 1000.0).astype(np.float32), f, NormalOperators.of(f, len(v), np.float32))
    assert single.dtype == np.float32
    np.testing.assert_allclose(single, normals, atol=1e-5)


def test_random_rigid_is_rigid(body_points: np.ndarray) -> None:
    pts = body_points[:500]
    moved, T = random_rigid(pts, np.random.default_rng(4), max_angle=math.pi, translation=1.0)
    np.testing.assert_allclose(pdist(moved), pdist(pts), atol=1e-12)
    np.testing.assert_allclose(moved, pts @ T[:3, :3].T + T[:3, 3], atol=1e-12)
    assert abs(np.linalg.det(T[:3, :3]) - 1) < 1e-12 and np.linalg.norm(T[:3, 3]) <= 1.0
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    _, T2 = random_rigid(pts, np.random.default_rng(4), max_angle=0.1, translation=0.0)
    assert np.degrees(math.acos((np.trace(T2[:3, :3]) - 1) / 2)) <= math.degrees(0.1) + 1e-9

"""The non-rigid refinement on shapes beyond a shape space: a limb thicker and longer than the template's,
a bump, and a hole the registration must not be drawn into."""

from __future__ import annotations

import numpy as np
import trimesh

from bodyfit.io.scans import sample_surface
from bodyfit.models.fitting.common.nonrigid import NonRigidConfig, NonRigidStage, refine_nonrigid
from bodyfit.models.fitting.common.surface import point_to_surface

# one stiff stage, pulls across the surface only: the refinement as a single-level ICP
SINGLE_LEVEL = NonRigidConfig(stages=(NonRigidStage(4.0, 0.04, 0.01, 3),), slide_from=1.0, slide_full=2.0)


def limb() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A capsule (a limb, 4 cm radius; vertices (V, 3), faces (F, 3)) and the same capsule with its upper
    half thickened by up to 2 cm and lengthened by 6 cm (V, 3): a change no shape space of the template
    holds, with its tip 6 cm from the template's."""
    mesh = trimesh.creation.capsule(height=0.2, radius=0.04, count=[24, 24])
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    target = v.copy()
    up = target[:, 2] > 0
    ramp = np.clip(target[:, 2] / 0.1, 0.0, 1.0)
    target[up, :2] *= ((0.04 + 0.02 * ramp[up]) / 0.04)[:, None]
    target[up, 2] += 0.06 * ramp[up]
    return v, f, target


def test_a_limb_beyond_the_shape_space_is_registered_to_the_millimetre() -> None:
    v, f, target = limb()
    points, _ = sample_surface(target, f, 20_000, seed=0)
    near = point_to_surface(refine_nonrigid(v, f, points), target, f) * 1000
    assert near.mean() < 1.0 and near.max() < 5.0
    single = point_to_surface(refine_nonrigid(v, f, points, SINGLE_LEVEL), target, f) * 1000
    assert single.mean() > 3.0 and single.max() > 15.0  # one stiff level leaves the tip 5 cm short


def test_a_bump_is_fitted_everywhere_within_a_few_millimetres() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    bump = 0.03 * np.exp(-((np.linalg.norm(v - [0.0, 0.0, 0.1], axis=1) / 0.04) ** 2))
    target = v * (1.0 + bump / 0.1)[:, None]
    points, _ = sample_surface(target, f, 20_000, seed=1)
    near = point_to_surface(refine_nonrigid(v, f, points), target, f) * 1000
    assert near.max() < 4.0


def test_a_hole_in_the_scan_does_not_draw_the_registration_to_its_rim() -> None:
    """A sphere scanned with a 4 cm cap missing, fitted from a 3 mm smaller sphere: the vertices over the
    hole follow the surface around it (their nearest scan points are on the rim, pulling sideways)."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    points, _ = sample_surface(v, f, 20_000, seed=2)
    top = np.array([0.0, 0.0, 0.1])
    points = points[np.linalg.norm(points - top, axis=1) > 0.04]
    moved = refine_nonrigid(v * 0.97, f, points)
    over_hole = np.linalg.norm(v - top, axis=1) < 0.03
    # the true correspondence: each vertex back at its place on the full sphere
    assert np.linalg.norm(moved[over_hole] - v[over_hole], axis=1).mean() < 0.003
    assert np.linalg.norm(moved[~over_hole] - v[~over_hole], axis=1).mean() < 0.0005

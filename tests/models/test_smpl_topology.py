"""SMPL topology through the stored correspondence: the asset, the two CC BY bodies it was built from, a
posed and moved SMPL-topology mesh, and bad input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bodyfit.models.body.model import BodyModel
from bodyfit.models.errors import NonFiniteError, ShapeError
from bodyfit.models.fitting.common.surface import point_to_surface
from bodyfit.models.fitting.registered.fitter import RegisteredFitter
from bodyfit.models.fitting.registered.smpl_topology import (
    SMPL_TO_BODY,
    SMPL_VERTICES,
    SOURCE_DIR,
    SOURCES,
    fit_smpl_meshes,
    read_obj,
    refine_smpl_fit,
    smpl_map,
)
from bodyfit.models.fitting.scan.fitter import ScanFitter

# Measured when the asset was built: 6.2 / 5.6 mm mean SMPL-vertex-to-surface distance.
MEAN_MM = 8.0
# The two sides of a symmetric rest pose read alike; a map that twists one limb reads it up to 28 degrees
# apart at the forearm's pro_sup and 8-11 at the ankles.
SIDE_GAP_DEG = {"pro_sup": 6.0, "arm_rot": 12.0, "elbow_flex": 4.0, "ankle_angle": 4.0, "knee_angle": 4.0}


@pytest.fixture(scope="module")
def model() -> BodyModel:
    return BodyModel.load()


@pytest.fixture(scope="module")
def bodies() -> list[tuple[np.ndarray, np.ndarray]]:
    return [read_obj(SOURCE_DIR / name) for name in SOURCES]


def test_map_asset_is_a_valid_correspondence(model: BodyModel) -> None:
    tmap = smpl_map()
    V = model.n_vertices
    assert tmap.faces.shape == (13776, 3) and tmap.faces.max() == SMPL_VERTICES - 1
    assert tmap.face.shape == (V,) and tmap.bary.shape == (V, 3) and tmap.weight.shape == (V,)
    np.testing.assert_allclose(tmap.bary.sum(axis=1), 1.0, atol=1e-9)
    assert tmap.bary.min() >= -1e-9
    assert tmap.weight.mean() > 0.95  # almost every vertex of ours lies on SMPL's surface


def test_rotation_between_frames() -> None:
    # SMPL faces +Z with its left hand toward +X; we face +X with +Z to the right.
    np.testing.assert_allclose(SMPL_TO_BODY @ [0, 0, 1], [1, 0, 0])
    np.testing.assert_allclose(SMPL_TO_BODY @ [1, 0, 0], [0, 0, -1])
    assert np.isclose(np.linalg.det(SMPL_TO_BODY), 1.0)


def test_the_cc_by_bodies_fit_through_the_map(
    model: BodyModel, bodies: list[tuple[np.ndarray, np.ndarray]]
) -> None:
    fit, distances = fit_smpl_meshes(RegisteredFitter(model), np.stack([v for v, _ in bodies]))
    assert distances.shape == (2, SMPL_VERTICES)
    assert (distances.mean(axis=1) * 1000 < MEAN_MM).all(), distances.mean(axis=1)
    assert all(r.limit_violations == 0 for r in fit.reports)
    # parameters in our frame (+Y up): the highest joint is above the pelvis
    assert (fit.joints[:, :, 1].max(axis=1) > fit.root[:, 1]).all()
    skel = model.skeleton
    for name, limit in SIDE_GAP_DEG.items():
        gap = np.degrees(
            fit.coordinates[:, skel.dof_index(f"{name}_l")] - fit.coordinates[:, skel.dof_index(f"{name}_r")]
        )
        assert (np.abs(gap) < limit).all(), (name, gap)


def test_a_fit_refined_on_the_mesh_surface_follows_its_hands_and_feet(
    model: BodyModel, bodies: list[tuple[np.ndarray, np.ndarray]]
) -> None:
    """The CC BY woman placed through the map, then refined on her mesh's surface: her vertices lie within
    4 mm of the registration on average (5.6 mm from the registered fit, whose hands and feet the map's
    correspondences hold off the surface), the parametric body itself is closer too (5.0 mm), in our frame,
    within the limits, and the steps are reported."""
    fitter = RegisteredFitter(model)
    verts, faces = bodies[1]
    placed, before = fit_smpl_meshes(fitter, verts)
    steps: list[tuple[int, int, str]] = []
    refined = refine_smpl_fit(
        ScanFitter(model, fitter=fitter), placed, verts, faces, progress=lambda *s: steps.append(s)
    )
    body = verts @ SMPL_TO_BODY.T
    after = point_to_surface(body, refined.registration, model.faces)
    parametric = point_to_surface(body, refined.vertices, model.faces)
    assert after.mean() < 4e-3 and np.percentile(after, 95) < 20e-3, (after.mean(), before.mean())
    assert parametric.mean() < 0.95 * before.mean() and refined.report.limit_violations == 0
    np.testing.assert_array_equal(refined.scan_to_body, np.eye(4))  # the points were in our frame
    assert [(d, t) for d, t, _ in steps] == [(0, 2), (1, 2), (2, 2)] and "refining" in steps[0][2]
    assert "orientation was searched" not in " ".join(refined.report.reasons)


def test_refine_checks_the_body_it_starts_from(
    model: BodyModel, bodies: list[tuple[np.ndarray, np.ndarray]]
) -> None:
    scanner = ScanFitter(model)
    points = bodies[0][0] @ SMPL_TO_BODY.T
    c, q, r = np.zeros(model.n_shape), model.bind_coordinates, np.zeros(3)
    with pytest.raises(ValueError, match=r"coordinates must be a finite \(46,\) array"):
        scanner.refine(points, c, q[:10], r)
    with pytest.raises(ValueError, match=r"root must be a finite \(3,\) array"):
        scanner.refine(points, c, q, np.array([0.0, np.nan, 0.0]))


def test_a_moved_smpl_mesh_fits_the_same(
    model: BodyModel, bodies: list[tuple[np.ndarray, np.ndarray]]
) -> None:
    verts = bodies[1][0]
    R = Rotation.from_euler("y", 120, degrees=True).as_matrix()
    moved = verts @ R.T + np.array([1.0, 0.2, -3.0])
    fitter = RegisteredFitter(model)
    _, d_still = fit_smpl_meshes(fitter, verts)
    _, d_moved = fit_smpl_meshes(fitter, moved)
    assert abs(d_still.mean() - d_moved.mean()) < 1.5e-3


def test_bad_smpl_input(model: BodyModel) -> None:
    fitter = RegisteredFitter(model)
    with pytest.raises(ShapeError, match="6890"):
        fit_smpl_meshes(fitter, np.zeros((1, 6000, 3)))
    bad = np.zeros((1, SMPL_VERTICES, 3))
    bad[0, 5, 1] = np.nan
    with pytest.raises(NonFiniteError):
        fit_smpl_meshes(fitter, bad)

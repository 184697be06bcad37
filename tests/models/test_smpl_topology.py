"""SMPL topology through the stored correspondence: the asset, the two CC BY bodies it was built from, a
posed and moved SMPL-topology mesh, and bad input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bodyfit.models.body.model import BodyModel
from bodyfit.models.errors import NonFiniteError, ShapeError
from bodyfit.models.fitting.registered import RegisteredFitter
from bodyfit.models.fitting.smpl_topology import (
    SMPL_TO_BODY,
    SMPL_VERTICES,
    SOURCE_DIR,
    SOURCES,
    fit_smpl_meshes,
    read_obj,
    smpl_map,
)

# Measured when the asset was built (BENCHMARKS.md): 10.4 / 9.4 mm mean SMPL-vertex-to-surface distance.
MEAN_MM = 12.0


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

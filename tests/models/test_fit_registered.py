"""Fitting registered meshes (our topology): recovery of known bodies, partial meshes, warm starts, held-out
anny bodies the model never saw, and every bad input."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from bodyfit.models.body.anny_posed import random_poses
from bodyfit.models.body.model import BodyModel
from bodyfit.models.errors import NonFiniteError, ShapeError
from bodyfit.models.fitting.registered import BodyFit, RegisteredFitter
from bodyfit.models.rotations import kabsch


@pytest.fixture(scope="module")
def model() -> BodyModel:
    return BodyModel.load()


@pytest.fixture(scope="module")
def fitter(model: BodyModel) -> RegisteredFitter:
    return RegisteredFitter(model)


@pytest.fixture(scope="module")
def known(model: BodyModel) -> dict[str, np.ndarray]:
    """Six bodies of the model in varied poses, turned and moved anywhere."""
    rng = np.random.default_rng(7)
    n = 6
    q = random_poses(model.skeleton, n, rng, spread=0.5)
    q[:, model.skeleton.dof_index("pelvis_rotation")] = rng.uniform(-3.0, 3.0, n)
    shape = rng.normal(size=(n, model.n_shape)) * 0.8
    root = rng.normal(size=(n, 3))
    out = model.forward(shape, q, root, dtype=torch.float64)
    return {
        "q": q,
        "shape": shape,
        "root": root,
        "vertices": out.vertices.numpy(),
        "joints": out.joints.numpy(),
    }


def test_kabsch_recovers_a_rigid_motion() -> None:
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3))
    R = Rotation.random(3, random_state=1).as_matrix()
    t = rng.normal(size=(3, 3))
    dst = np.einsum("bij,vj->bvi", R, src) + t[:, None]
    R_fit, t_fit = kabsch(src, dst, np.ones((3, 50)))
    np.testing.assert_allclose(R_fit, R, atol=1e-10)
    np.testing.assert_allclose(t_fit, t, atol=1e-10)


def test_fit_recovers_known_bodies(fitter: RegisteredFitter, known: dict[str, np.ndarray]) -> None:
    fit = fitter.fit(known["vertices"])
    errors = np.array([r.distances.mean for r in fit.reports])
    # mm over all 13k vertices; the default stages trade the last fraction of a millimetre for speed.
    assert errors.mean() < 1.5 and errors.max() < 3.0, errors
    joint_err = np.linalg.norm(fit.joints - known["joints"], axis=-1)
    assert joint_err.mean() < 0.01  # metres
    assert all(r.limit_violations == 0 and r.confident for r in fit.reports)
    assert fit.coordinates.shape == known["q"].shape and fit.shape.shape == known["shape"].shape
    lo, hi = fitter.model.skeleton.ranges.T
    assert ((fit.coordinates >= lo) & (fit.coordinates <= hi)).all()
    # The report is consistent with the returned registration.
    d = np.linalg.norm(fit.vertices - known["vertices"], axis=-1) * 1000
    np.testing.assert_allclose([r.distances.mean for r in fit.reports], d.mean(axis=1), rtol=1e-6)
    assert fit.reports[0].distances.p95 >= fit.reports[0].distances.median


def test_missing_vertices_are_ignored(fitter: RegisteredFitter, known: dict[str, np.ndarray]) -> None:
    """A third of every mesh missing (weight 0) and garbage there: the fit follows the rest."""
    x = known["vertices"][:3].copy()
    rng = np.random.default_rng(3)
    w = (rng.uniform(size=x.shape[:2]) > 0.33).astype(np.float64)
    x[w == 0] += 0.5  # far off: would ruin the fit if it were used
    fit = fitter.fit(x, weights=w)
    true_err = np.linalg.norm(fit.vertices - known["vertices"][:3], axis=-1).mean(axis=1) * 1000
    assert true_err.max() < 3.0, true_err


def test_warm_start_from_the_answer(fitter: RegisteredFitter, known: dict[str, np.ndarray]) -> None:
    x = known["vertices"][:2]
    init = BodyFit(known["shape"][:2], known["q"][:2], known["root"][:2], x, known["joints"][:2])
    fit = fitter.fit(x, init=init)
    assert max(r.distances.mean for r in fit.reports) < 0.2


def test_shared_shape_fits_one_person(fitter: RegisteredFitter, model: BodyModel) -> None:
    rng = np.random.default_rng(11)
    q = random_poses(model.skeleton, 4, rng, spread=0.4)
    shape = np.repeat(rng.normal(size=(1, model.n_shape)) * 0.8, 4, axis=0)
    x = model.forward(shape, q, dtype=torch.float64).vertices.numpy()
    fit = fitter.fit(x, shared_shape=True)
    assert np.ptp(fit.shape, axis=0).max() == 0.0  # one shape for every frame
    assert max(r.distances.mean for r in fit.reports) < 2.0


def test_not_a_body_is_not_confident(fitter: RegisteredFitter, model: BodyModel) -> None:
    rng = np.random.default_rng(5)
    blob = rng.normal(size=(1, model.n_vertices, 3)) * 0.3
    fit = fitter.fit(blob)
    report = fit.reports[0]
    assert not report.confident
    assert "mean vertex error" in report.reasons[0]
    assert report.limit_violations == 0


@pytest.mark.parametrize(
    ("make", "error", "words"),
    [
        (lambda V: np.zeros((2, V - 1, 3)), ShapeError, "our template's vertices"),
        (lambda V: np.zeros((2, V, 2)), ShapeError, "(B, 13348, 3)"),
        (lambda V: np.full((1, V, 3), np.nan), NonFiniteError, "NaN"),
    ],
)
def test_bad_meshes_raise_clear_errors(
    fitter: RegisteredFitter, make: Callable[[int], np.ndarray], error: type[Exception], words: str
) -> None:
    with pytest.raises(error) as info:
        fitter.fit(make(fitter.model.n_vertices))
    assert words in str(info.value)


def test_bad_weights_raise_clear_errors(fitter: RegisteredFitter, known: dict[str, np.ndarray]) -> None:
    x = known["vertices"][:1]
    with pytest.raises(ShapeError, match="weights must have shape"):
        fitter.fit(x, weights=np.ones((1, 5)))
    with pytest.raises(ShapeError, match="non-negative"):
        fitter.fit(x, weights=-np.ones(x.shape[:2]))
    with pytest.raises(ShapeError, match="non-negative"):
        fitter.fit(x, weights=np.zeros(x.shape[:2]))


@pytest.mark.build
def test_held_out_anny_bodies_fit_within_two_millimetres(fitter: RegisteredFitter, model: BodyModel) -> None:
    """anny bodies from a seed the build never used, posed by anny's own skinning: not in the model's span,
    so this measures the model and the fitter together (the issue's target: mean <= 2 mm)."""
    pytest.importorskip("anny")
    from bodyfit.models.body.anny_posed import posed_anny_bodies
    from bodyfit.models.body.anny_source import AnnySource
    from bodyfit.models.build_assets import default_cache_dir

    src = AnnySource(Path(default_cache_dir()))
    bodies = posed_anny_bodies(src, model.skeleton, 8, seed=31337)
    fit = fitter.fit(bodies.vertices)
    errors = np.array([r.distances.mean for r in fit.reports])
    assert errors.mean() <= 2.0, errors
    assert all(r.limit_violations == 0 for r in fit.reports)
    # The pose is recovered too (ground truth coordinates; pelvis upright in these bodies).
    knee = [model.skeleton.dof_index(n) for n in ("knee_angle_r", "knee_angle_l")]
    assert np.degrees(np.abs(fit.coordinates[:, knee] - bodies.q[:, knee])).mean() < 6.0

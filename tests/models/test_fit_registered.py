"""Fitting registered meshes (our topology): recovery of known bodies, partial meshes, warm starts, held-out
anny bodies the model never saw, and every bad input."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from bodyfit.models.body.anny_posed import random_poses
from bodyfit.models.body.model import BodyModel
from bodyfit.models.errors import NonFiniteError, ShapeError
from bodyfit.models.fitting.registered.fitter import (
    BodyFit,
    RegisteredFitConfig,
    RegisteredFitter,
    Stage,
    vertex_term,
)
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


def test_stage_jacobian_is_the_derivative_of_the_vertices(
    model: BodyModel, known: dict[str, np.ndarray]
) -> None:
    """The forward-difference Jacobian in ``optimise``'s variables agrees with forward-mode autodiff."""
    fitter = RegisteredFitter(model, RegisteredFitConfig(dtype=torch.float64))
    stage = Stage(name="pose", coordinates="all", shape="bone", vertices="subset", iterations=1)
    z = fitter.start_state(known["q"][:2], known["root"][:2], known["shape"][:2])
    J = fitter.stage_jacobian(stage, z, "subset", step=1e-6)  # (2, 3V', P)
    n_bone, n_dof = model.n_bone, model.skeleton.n_dof
    _, s_r, s_c = fitter._scales
    assert J.shape == (2, 3 * len(fitter.index["subset"]), n_dof + 3 + n_bone)

    def vertices(Z: torch.Tensor) -> torch.Tensor:
        u, r, c = Z[:, :n_dof], Z[:, n_dof : n_dof + 3], z[2].clone()
        c[:, :n_bone] = Z[:, n_dof + 3 :]
        return fitter.decoders["subset"](c * s_c, fitter.coordinates(u), r * s_r)[0].flatten(1) * 1000.0

    Z0 = torch.cat([z[0], z[1], z[2][:, :n_bone]], 1)
    d = torch.as_tensor(np.random.default_rng(5).normal(size=Z0.shape))
    expected = torch.func.jvp(vertices, (Z0,), (d,))[1]
    np.testing.assert_allclose((J @ d[..., None])[..., 0], expected, atol=1e-3 * expected.abs().max().item())


def test_preconditioner_unit_moves_the_subset_by_one_millimetre(model: BodyModel) -> None:
    """One preconditioned unit of any parameter moves the subset's vertices by about 1 mm RMS at the bind
    pose (central differences in float64; parameters clamped at 1e-3 mm per unit are skipped)."""
    fitter = RegisteredFitter(model, RegisteredFitConfig(dtype=torch.float64))
    skel, n_dof, ns = model.skeleton, model.skeleton.n_dof, model.n_shape
    s_u, s_r, s_c = fitter._scales
    scale = torch.cat([s_u, s_r, s_c])
    p0 = torch.cat([
        skel.to_unbounded(torch.as_tensor(skel.inside(model.bind_coordinates, 0.1)[None])),
        torch.zeros(1, 3 + ns, dtype=torch.float64),
    ], dim=1)  # fmt: skip

    def vertices(p: torch.Tensor) -> torch.Tensor:
        u, r, c = p[:, :n_dof], p[:, n_dof : n_dof + 3], p[:, n_dof + 3 :]
        return fitter.decoders["subset"](c, skel.from_unbounded(u), r)[0] * 1000.0

    h = 1e-4
    checked = 0
    for k in np.random.default_rng(3).permutation(len(scale))[:24]:
        if scale[k] >= 999.0:
            continue
        step = torch.zeros_like(p0)
        step[0, k] = h * scale[k]
        moved = (vertices(p0 + step) - vertices(p0 - step)) / (2 * h)  # mm per preconditioned unit
        assert moved.norm(dim=-1).pow(2).mean().sqrt().item() == pytest.approx(1.0, rel=1e-3), int(k)
        checked += 1
    assert checked >= 12


def test_building_a_fitter_does_not_import_the_compiler() -> None:
    """The preconditioner's derivatives stay in reverse mode: torch's forward mode imports torch._dynamo,
    a second on every service start and every command line fit."""
    code = (
        "import sys\n"
        "from bodyfit.models.body.model import BodyModel\n"
        "from bodyfit.models.fitting.registered.fitter import RegisteredFitter\n"
        "RegisteredFitter(BodyModel.load())\n"
        "print('torch._dynamo' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "False"


def _optimised_errors(
    fitter: RegisteredFitter, stage: Stage, x: torch.Tensor, q0: np.ndarray, root: np.ndarray, c0: np.ndarray
) -> list[float]:
    """Mean vertex errors (mm) against x (B, V_subset, 3) after ``stage`` from (q0, root, c0): without the
    Gauss-Newton metric, then with it. The metric has one (P, P) block per problem."""
    term = vertex_term(x, torch.ones(x.shape[:2]))
    errors = []
    for use_metric in (False, True):
        z = fitter.start_state(q0, root, c0)
        metric = fitter.metric(stage, z, "subset") if use_metric else None
        n = len(q0) // len(c0) * (fitter.model.skeleton.n_dof + 3) + c0.shape[1]  # poses and roots, shape
        assert metric is None or metric.shape == (len(c0), n, n)
        fitter.optimise(stage, z, term, metric)
        c, q, r = fitter.parameters(z)
        v = fitter.decoders["subset"](c.float(), q.float(), r.float())[0] * 1000.0
        errors.append((v - x).norm(dim=-1).mean().item())
    return errors


def test_a_gauss_newton_metric_speeds_up_optimise(
    fitter: RegisteredFitter, known: dict[str, np.ndarray]
) -> None:
    """From a start 0.1 rad off in every coordinate, five iterations in the metric's variables fit the
    bodies far better than five with the diagonal preconditioner alone."""
    stage = Stage(name="all", coordinates="all", shape="all", vertices="subset", iterations=5)
    x = torch.as_tensor(known["vertices"][:3][:, fitter.index["subset"]] * 1000.0, dtype=torch.float32)
    q0 = known["q"][:3] + np.random.default_rng(2).normal(scale=0.1, size=known["q"][:3].shape)
    errors = _optimised_errors(fitter, stage, x, q0, known["root"][:3], known["shape"][:3])
    assert errors[1] < 0.5 * errors[0], errors


def test_a_gauss_newton_metric_speeds_up_a_shared_shape_fit(
    fitter: RegisteredFitter, known: dict[str, np.ndarray]
) -> None:
    """Three poses of one person, one shape for all (one problem), from the mean shape: ten iterations in the
    metric's variables (the poses' blocks, their couplings to the shape and the shape's block summed) fit
    far better than ten without (17.0 against 9.6 mm; 18.9 with the couplings left out, 21.2 with one pose's
    shape block instead of the sum)."""
    stage = Stage(name="all", coordinates="all", shape="all", vertices="subset", iterations=10)
    shape = np.repeat(known["shape"][:1], 3, axis=0)
    out = fitter.decoders["subset"](
        *(torch.as_tensor(a, dtype=torch.float32) for a in (shape, known["q"][:3], known["root"][:3]))
    )
    x = out[0].detach() * 1000.0
    q0 = known["q"][:3] + np.random.default_rng(3).normal(scale=0.1, size=known["q"][:3].shape)
    errors = _optimised_errors(fitter, stage, x, q0, known["root"][:3], np.zeros((1, shape.shape[1])))
    assert errors[1] < 0.7 * errors[0], errors


def test_a_metric_that_is_not_positive_definite_is_not_used(
    fitter: RegisteredFitter, known: dict[str, np.ndarray]
) -> None:
    stage = Stage(name="all", coordinates="all", shape="all", vertices="subset", iterations=10)
    x = torch.as_tensor(known["vertices"][:2][:, fitter.index["subset"]] * 1000.0, dtype=torch.float32)
    term = vertex_term(x, torch.ones(x.shape[:2]))
    q0 = known["q"][:2] + 0.05
    z = fitter.start_state(q0, known["root"][:2], known["shape"][:2])
    metric = fitter.metric(stage, z, "subset")
    metric[1] = 0.0  # singular
    before = term(fitter.decoders["subset"](*(t.float() for t in fitter.parameters(z)))[0] * 1000.0)
    fitter.optimise(stage, z, term, metric)
    after = term(fitter.decoders["subset"](*(t.float() for t in fitter.parameters(z)))[0] * 1000.0)
    assert torch.isfinite(after).all() and (after < 0.5 * before).all(), (before, after)

"""Bodies from measurements: the shape coefficients whose body has the requested measurements.

Any subset of the measurements may be given, down to stature and mass alone. The shape is the maximum a
posteriori estimate under the shape prior (standard normal coefficients, or a given Gaussian) and
Gaussian measurement errors of one tolerance (5 mm for lengths, 8 mm for circumferences, 0.5 kg):

    minimise  sum_m ((f_m(c) - t_m) / tol_m)^2 + (c - mu)^T Lambda (c - mu)

so that the measurements given are met and the rest of the body stays where the prior puts it. The
measurements are smooth and nearly linear in the coefficients (lengths exactly so in the bone
coefficients, circumferences and mass nearly), so Gauss-Newton converges in a few steps. Its Jacobian is
taken once by central differences at the prior mean and then updated per body from each step's change
(C. G. Broyden, "A class of methods for solving nonlinear simultaneous equations", Mathematics of
Computation 19(92), 1965): one body evaluation per step, batched over many bodies.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bodyfit.models.anthropometry.definitions import MEASUREMENTS
from bodyfit.models.anthropometry.measure import body_in_pose, measure_torch
from bodyfit.models.anthropometry.ranges import (
    ANSUR_MEANS,
    SEXES,
    ImplausibleMeasurementError,
    check_measurements,
)
from bodyfit.models.anthropometry.regions import topology
from bodyfit.models.body.model import BodyModel

NAMES = list(MEASUREMENTS)
# Tolerance per kind: the error a measurer's repeat allows (ANSUR II's observer error is 2-10 mm); for the
# mass, a body's own swing over a day (meals, fluid), which is larger than a scale's error (0.1 kg). At
# 1 kg the mass weighs no more than one tape, and bodies built from a full row miss it by 1.5 kg to meet
# the tapes 0.2 mm closer (benchmarks/anthropometry.py, docs/anthropometry.md).
TOLERANCE = {"height": 0.005, "length": 0.005, "breadth": 0.005, "circumference": 0.008, "mass": 0.5}
_TOL = np.array([TOLERANCE[MEASUREMENTS[n].kind] for n in NAMES])
_STEPS = 10
_FD_STEP = 0.25
_CHUNK = 32
_HALVINGS = 4
MAX_SD = 8.0
"""Largest coefficient (in the model's standard deviations) a built body takes, within the service's
plausible shapes (10): one in ten NHANES men (the heaviest) needs more than 5 to be built."""


@dataclass(frozen=True)
class BodyFromMeasurements:
    """The body built from measurements.

    Attributes:
        shape: (n_shape,) shape coefficients.
        achieved: every measurement of that body (name -> value).
        requested: the values asked for, under their ANSUR II names (aliases resolved).
        residuals: achieved minus requested, for the measurements requested.
        unmet: the requested measurements missed by more than their tolerance (:data:`TOLERANCE`): the
            set could not all be met in the model's shape space.
    """

    shape: np.ndarray
    achieved: dict[str, float]
    requested: dict[str, float]
    residuals: dict[str, float]
    unmet: list[str]

    @property
    def flagged(self) -> bool:
        """True when some requested measurement is not met within its tolerance."""
        return bool(self.unmet)


def evaluate(model: BodyModel, shapes: np.ndarray) -> np.ndarray:
    """Every measurement (B, M) in :data:`NAMES` order of shapes (B, n_shape), in the measuring posture."""
    topo = topology(model)
    rows = []
    with torch.no_grad():
        for a in range(0, len(shapes), _CHUNK):
            c = torch.as_tensor(shapes[a : a + _CHUNK], dtype=torch.float32)
            v, j = body_in_pose(model, c)
            out = measure_torch(topo, v, j)
            rows.append(torch.stack([out[n] for n in NAMES], 1).double().numpy())
    return np.concatenate(rows)


def mean_jacobian(model: BodyModel) -> tuple[np.ndarray, np.ndarray]:
    """Measurements (M,) of the mean body and their Jacobian (M, n_shape) there, by central differences;
    cached per model."""

    def build() -> tuple[np.ndarray, np.ndarray]:
        K = model.n_shape
        probes = np.concatenate([np.zeros((1, K)), _FD_STEP * np.eye(K), -_FD_STEP * np.eye(K)])
        f = evaluate(model, probes)
        return f[0], (f[1 : K + 1] - f[K + 1 :]).T / (2 * _FD_STEP)

    return model.derived("anthropometry.mean_jacobian", build)


def fit_measurements(
    model: BodyModel,
    targets: np.ndarray,
    prior_mean: np.ndarray | None = None,
    prior_precision: np.ndarray | None = None,
    steps: int = _STEPS,
    tolerance: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Shapes for many bodies at once (see the module docstring).

    Args:
        targets: (B, M) requested values in :data:`NAMES` order, NaN where not requested (unchecked: see
            :func:`check_measurements`).
        prior_mean: (n_shape,) or (B, n_shape), default zeros; prior_precision: (n_shape, n_shape),
            default the identity.
        steps: Gauss-Newton steps.
        tolerance: (M,) each measurement's tolerance, default :data:`TOLERANCE` by kind.
    Returns:
        shapes (B, n_shape) and every measurement of them (B, M).
    """
    T = np.asarray(targets, np.float64)
    B, K = len(T), model.n_shape
    mu = np.broadcast_to(np.zeros(K) if prior_mean is None else np.asarray(prior_mean, np.float64), (B, K))
    P = np.eye(K) if prior_precision is None else np.asarray(prior_precision, np.float64)
    given = np.isfinite(T)
    tol = _TOL if tolerance is None else np.asarray(tolerance, np.float64)
    w = np.where(given, 1.0 / tol, 0.0)  # (B, M) residual weights
    goal = np.where(given, T, 0.0)
    f0, J0 = mean_jacobian(model)
    J = np.broadcast_to(J0, (B, *J0.shape)).copy()
    c = mu.copy()
    f = f0[None].repeat(B, 0) if not np.any(mu) else evaluate(model, c)
    for _ in range(steps):
        Jw = J * w[..., None]
        A = np.einsum("bmk,bml->bkl", Jw, Jw) + P
        g = np.einsum("bmk,bm->bk", Jw, (f - goal) * w) + np.einsum("kl,bl->bk", P, c - mu)
        delta = _bounded(c, -np.linalg.solve(A, g[..., None])[..., 0])
        f_new = evaluate(model, c + delta)
        for _ in range(_HALVINGS):  # a step into bodies the shape space does not close: take half of it
            lost = ~np.isfinite(f_new).all(1)
            if not lost.any():
                break
            delta[lost] *= 0.5
            f_new[lost] = evaluate(model, c[lost] + delta[lost])
        stuck = ~np.isfinite(f_new).all(1)  # no step of this size closes the skin: stay
        delta[stuck], f_new[stuck] = 0.0, f[stuck]
        # Broyden's rank-one update: J delta reproduces the change the step made.
        change = f_new - f - np.einsum("bmk,bk->bm", J, delta)
        J += change[..., None] * delta[:, None] / np.maximum((delta**2).sum(1), 1e-12)[:, None, None]
        c, f = c + delta, f_new
    return c, f


def _bounded(c: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """``delta`` (B, K) shortened per body so that ``c + delta`` stays within :data:`MAX_SD` of the mean: the
    linearisation of an extreme request can overshoot far beyond where the model has bodies."""
    reach = np.abs(c + delta).max(1)
    scale = np.where(
        reach > MAX_SD, np.maximum(MAX_SD - np.abs(c).max(1), 0.0) / np.abs(delta).max(1).clip(1e-12), 1.0
    )
    return delta * np.minimum(scale, 1.0)[:, None]


def gaussian_prior(shapes: np.ndarray, shrink: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """A Gaussian prior learned from shapes built for a population's measurements.

    The covariance is shrunk towards its diagonal by ``shrink`` so that it stays well conditioned for a few
    hundred bodies in the shape space's dimensions (O. Ledoit and M. Wolf, "A well-conditioned estimator
    for large-dimensional covariance matrices", Journal of Multivariate Analysis 88(2), 2004).

    Args:
        shapes: (N, n_shape).
    Returns:
        mean (n_shape,) and precision (n_shape, n_shape), for :func:`fit_measurements`.
    """
    c = np.asarray(shapes, np.float64)
    cov = np.cov(c, rowvar=False)
    cov = (1.0 - shrink) * cov + shrink * np.diag(np.diag(cov))
    return c.mean(0), np.linalg.inv(cov)


# The mean body is matched to within a few tolerances only: some definitions differ from ANSUR II's by more
# than one (docs/anthropometry.md), and meeting them all would push the prior's mean to the edge of the
# shape space.
_MEAN_SLACK = 4.0


def sex_prior_mean(model: BodyModel, sex: str) -> np.ndarray:
    """(n_shape,) the shape of the mean ANSUR II man or woman (:data:`ANSUR_MEANS`) under the standard
    normal prior: the prior mean of bodies built for that sex. Cached per model."""

    def build() -> np.ndarray:
        column = SEXES.index(sex)
        target = np.array([[ANSUR_MEANS[n][column] if n in ANSUR_MEANS else np.nan for n in NAMES]])
        return fit_measurements(model, target, tolerance=_MEAN_SLACK * _TOL)[0][0]

    return model.derived(f"anthropometry.sex_prior_mean.{sex}", build)


def shape_from_measurements(
    model: BodyModel,
    measurements: dict[str, float],
    sex: str | None = None,
    prior_mean: np.ndarray | None = None,
    prior_precision: np.ndarray | None = None,
) -> BodyFromMeasurements:
    """The body with the requested measurements (see the module docstring).

    Args:
        model: the body model.
        measurements: name (or alias: "mass", "height", "waist", ...) -> value in metres, kilograms for the
            mass; any subset of :data:`MEASUREMENTS`.
        sex: "male", "female" or None: the plausible ranges the values are checked against, and the prior's
            mean (:func:`sex_prior_mean`; the model's mean body for None).
        prior_mean, prior_precision: a Gaussian prior over the coefficients (default: mean as above,
            precision the identity, the model's own spread).
    Returns:
        :class:`BodyFromMeasurements`; ``flagged`` when the set could not all be met.
    Raises:
        UnknownMeasurementError: a name is not known (the closest names are suggested).
        ImplausibleMeasurementError: a value outside its plausible range (named, with the range) or a
            height out of proportion to the stature.
    """
    wanted = check_measurements(measurements, sex)
    if not wanted:
        raise ImplausibleMeasurementError("give at least one measurement, e.g. {'stature': 1.75, 'mass': 70}")
    target = np.full((1, len(NAMES)), np.nan)
    for name, value in wanted.items():
        target[0, NAMES.index(name)] = value
    if prior_mean is None and sex is not None:
        prior_mean = sex_prior_mean(model, sex)
    shape, achieved = fit_measurements(model, target, prior_mean, prior_precision)
    values = dict(zip(NAMES, achieved[0].tolist()))
    residuals = {n: values[n] - wanted[n] for n in wanted}
    unmet = [n for n, r in residuals.items() if abs(r) > TOLERANCE[MEASUREMENTS[n].kind]]
    return BodyFromMeasurements(shape[0], values, dict(wanted), residuals, unmet)

"""A fit's predicted registration error: the mean distance (mm) of its registration's vertices to the true
body, with an interval, from what the fit can see of itself (its distances both ways, coverage, the
agreement of its branches, how far its pose and shape lie from the prior, how it was asked).

The estimate is three linear quantile regressions of the log error on :data:`FEATURES` (the 10%, 50% and
90% quantiles; R. Koenker and G. Bassett, "Regression Quantiles", Econometrica 46(1), 1978), fitted by
``benchmarks/calibrate_quality.py`` to raw-scan fits of held-out bodies in whole-body poses under every
corruption of the scan benchmark, with the orientation searched and hinted, and shipped as
``quality_model.json`` beside this module.

The confidence rule: a fit is confident when the upper end of its interval (the 90% quantile) lies below
the model's ``confident_below_mm`` (chosen at calibration, on out-of-fold predictions, so that no
calibration fit over :data:`BAD_MM` is confident, with a margin) and no hard reason (joint limits, too few
inliers, a head-and-shoulders fit, a height hint the fit disagrees with) says otherwise.

Features are clipped to the range they took at calibration (a linear model must not extrapolate), and a
missing or non-finite feature takes its worst calibrated value: a fit that cannot be measured is not
trusted.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import linprog

MODEL_PATH = Path(__file__).with_name("quality_model.json")
BAD_MM = 25.0  # a fit this far off (mean registration error) must never be reported confident
QUANTILES = (0.1, 0.5, 0.9)
PELVIS_DOFS = 3  # the first coordinates place the body in space: not part of the pose prior
NEAR_LIMIT = 0.02  # of a coordinate's range: a coordinate this close to a limit counts as pinned there

# name -> whether a larger value means a worse fit (the direction a monotone estimate should follow)
FEATURES: dict[str, bool] = {
    "log_inlier_mean": True,  # log mm: the inlier scan points' mean distance
    "log_scan_to_model_mean": True,  # log mm: every scan point's mean distance
    "log_scan_to_model_p95": True,
    "log_model_to_scan_mean": True,  # log mm: the body surface's mean distance to the scan
    "log_model_to_scan_p95": True,
    "outlier_fraction": True,  # 1 - inlier fraction
    "uncovered_fraction": True,  # 1 - coverage
    "unexplained_fraction": True,  # share of the cleaned scan far from the fit (a limb left out)
    "unsupported_fraction": True,  # share of the body far from the scan
    "largest_gap_fraction": True,  # largest connected region of the body far from the scan
    "log_nonrigid_offset": True,  # log mm: how far the non-rigid registration moved from the model
    "branch_disagreement": True,  # relative gap between the branches' scores
    "single_view": True,
    "head_and_shoulders": True,
    "orientation_searched": True,
    "pose_distance": True,  # rms of (q - bind) / range over the pose's coordinates
    "pinned_fraction": True,  # share of the pose's coordinates at a joint limit
    "shape_distance": True,  # rms of the shape coefficients (unit normal under the prior)
}


def _float(value: Any) -> float:
    """``value`` as a float; NaN when it is none."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def _log_mm(value: Any) -> float:
    """log(mm + 0.1) of a distance in mm; NaN when missing."""
    mm = _float(value)
    return math.log(max(mm, 0.0) + 0.1) if math.isfinite(mm) else math.nan


def _stat(report: Mapping[str, Any], key: str, field: str) -> float:
    entry = report.get(key)
    return math.nan if not isinstance(entry, Mapping) else _log_mm(entry.get(field))


def _number(extra: Mapping[str, Any], key: str) -> float:
    return _float(extra.get(key))


def _branch_disagreement(scores: Any) -> float:
    """(max - min) / min of the branches' scores (0 for one branch)."""
    if not isinstance(scores, list | tuple) or len(scores) < 2:
        return 0.0
    s = np.asarray(scores, np.float64)
    if not np.isfinite(s).all() or s.min() <= 0:
        return math.nan
    return float((s.max() - s.min()) / s.min())


def prior_distance(
    coordinates: np.ndarray, shape: np.ndarray, bind: np.ndarray, ranges: np.ndarray
) -> dict[str, float]:
    """How far a fit's pose and shape lie from the prior: ``pose`` the rms of (q - bind) / range over the
    pose's coordinates (n_dof,) (the pelvis's left out: they place the body), ``pinned`` the share of them
    within :data:`NEAR_LIMIT` of a joint limit (``ranges`` (n_dof, 2)), ``shape`` the rms of the shape
    coefficients (n_shape,; unit normal under the prior)."""
    q = np.asarray(coordinates, np.float64)[PELVIS_DOFS:]
    lo, hi = ranges[PELVIS_DOFS:, 0], ranges[PELVIS_DOFS:, 1]
    span = np.maximum(hi - lo, 1e-9)
    pinned = (q - lo < NEAR_LIMIT * span) | (hi - q < NEAR_LIMIT * span)
    c = np.asarray(shape, np.float64)
    return {
        "pose": round(float(np.sqrt(np.mean(((q - np.asarray(bind)[PELVIS_DOFS:]) / span) ** 2))), 4),
        "pinned": round(float(pinned.mean()), 4),
        "shape": round(float(np.sqrt(np.mean(c**2))) if c.size else 0.0, 4),
    }


def scan_features(report: Mapping[str, Any]) -> np.ndarray:
    """(len(FEATURES),) the features of a raw-scan fit from its report as a dictionary
    (:meth:`FitReport.to_dict`; ``extra["prior_distance"]`` from :func:`prior_distance`); NaN where the
    report lacks an entry."""
    extra = report.get("extra") or {}
    prior = extra.get("prior_distance") or {}
    values = {
        "log_inlier_mean": _stat(report, "distances", "mean"),
        "log_scan_to_model_mean": _stat(report, "scan_to_model", "mean"),
        "log_scan_to_model_p95": _stat(report, "scan_to_model", "p95"),
        "log_model_to_scan_mean": _stat(report, "model_to_scan", "mean"),
        "log_model_to_scan_p95": _stat(report, "model_to_scan", "p95"),
        "outlier_fraction": 1.0 - _number(extra, "inlier_fraction"),
        "uncovered_fraction": 1.0 - _number(extra, "coverage"),
        "unexplained_fraction": _number(extra, "unexplained_fraction"),
        "unsupported_fraction": _number(extra, "unsupported_fraction"),
        "largest_gap_fraction": _number(extra, "largest_gap_fraction"),
        "log_nonrigid_offset": _log_mm(extra.get("nonrigid_offset_mm")),
        "branch_disagreement": _branch_disagreement(extra.get("branch_scores")),
        "single_view": float(extra.get("single_view") is not None),
        "head_and_shoulders": float(extra.get("fitted_part", "whole body") != "whole body"),
        "orientation_searched": float(bool(extra.get("orientation_searched", True))),
        "pose_distance": _number(prior, "pose"),
        "pinned_fraction": _number(prior, "pinned"),
        "shape_distance": _number(prior, "shape"),
    }
    return np.array([values[name] for name in FEATURES], np.float64)


@dataclass(frozen=True)
class Prediction:
    """A predicted registration error (mm), its interval (mm) and whether it is confident."""

    error_mm: float
    interval_mm: tuple[float, float]
    confident: bool


@dataclass(frozen=True)
class QualityModel:
    """Quantile regressions of the log error (mm) on standardised, clipped features.

    lo, hi (n_features,): the features' range at calibration; mean, scale (n_features,): the standardisation;
    coefficients (len(QUANTILES), n_features + 1): per quantile, the intercept then the weights;
    confident_below_mm: the confidence rule's bound on the upper quantile.
    """

    lo: np.ndarray
    hi: np.ndarray
    mean: np.ndarray
    scale: np.ndarray
    coefficients: np.ndarray
    confident_below_mm: float

    def standardised(self, features: np.ndarray) -> np.ndarray:
        """(..., n_features) features clipped to the calibrated range (a non-finite one to its worse end)
        and standardised."""
        x = np.asarray(features, np.float64)
        worst = np.where(np.array(list(FEATURES.values())), self.hi, self.lo)
        x = np.where(np.isfinite(x), x, worst)
        return (np.clip(x, self.lo, self.hi) - self.mean) / self.scale

    def quantiles(self, features: np.ndarray) -> np.ndarray:
        """(..., len(QUANTILES)) the predicted error's quantiles (mm), in increasing order, of features
        (..., n_features)."""
        z = self.standardised(features)
        logs = self.coefficients[:, 0] + z @ self.coefficients[:, 1:].T
        return np.exp(np.sort(logs, axis=-1))

    def predict(self, features: np.ndarray) -> Prediction:
        """The prediction for one fit's features (n_features,)."""
        low, mid, high = (float(v) for v in self.quantiles(features))
        return Prediction(mid, (low, high), high < self.confident_below_mm)

    def to_json(self) -> dict[str, Any]:
        return {
            "features": list(FEATURES),
            "quantiles": list(QUANTILES),
            "lo": self.lo.tolist(),
            "hi": self.hi.tolist(),
            "mean": self.mean.tolist(),
            "scale": self.scale.tolist(),
            "coefficients": self.coefficients.tolist(),
            "confident_below_mm": self.confident_below_mm,
        }

    @classmethod
    def from_json(cls, doc: Mapping[str, Any]) -> QualityModel:
        if list(doc["features"]) != list(FEATURES) or list(doc["quantiles"]) != list(QUANTILES):
            raise ValueError("the quality model was calibrated on other features; run calibrate_quality.py")

        def array(key: str) -> np.ndarray:
            return np.asarray(doc[key], np.float64)

        return cls(
            array("lo"),
            array("hi"),
            array("mean"),
            array("scale"),
            array("coefficients"),
            float(doc["confident_below_mm"]),
        )


@lru_cache(maxsize=1)
def shipped_model() -> QualityModel:
    """The calibrated model shipped with the package (:data:`MODEL_PATH`)."""
    return QualityModel.from_json(json.loads(MODEL_PATH.read_text()))


def quantile_regression(X: np.ndarray, y: np.ndarray, tau: float, l1: float = 0.0) -> np.ndarray:
    """(n_features + 1,) intercept and weights minimising the pinball loss of quantile ``tau`` of y (n,) on
    X (n, n_features), plus ``l1`` times the weights' absolute sum (not the intercept's), as a linear
    programme (Koenker and Bassett, "Regression Quantiles", Econometrica 46(1), 1978). With X's columns
    those of :data:`FEATURES`, the weight of each feature marked worse-when-larger is kept non-negative.
    """
    n, p = X.shape
    A = np.hstack([np.ones((n, 1)), X])
    # variables: beta+ (p+1), beta- (p+1), residual+ (n), residual- (n), all >= 0
    penalty = np.r_[0.0, np.full(p, l1)]
    cost = np.r_[penalty, penalty, np.full(n, tau), np.full(n, 1.0 - tau)]
    eye = np.eye(n)
    # a weight of a feature where larger means worse (FEATURES) is kept >= 0: the estimate is monotone in it
    worse = np.array(list(FEATURES.values())) if p == len(FEATURES) else np.zeros(p, bool)
    bounds = [(0, None)] * (p + 1) + [(0, None)] + [(0, 0) if w else (0, None) for w in worse]
    bounds += [(0, None)] * (2 * n)
    solved = linprog(cost, A_eq=np.hstack([A, -A, eye, -eye]), b_eq=y, bounds=bounds, method="highs")
    if not solved.success:
        raise ValueError(f"quantile regression failed: {solved.message}")
    return solved.x[: p + 1] - solved.x[p + 1 : 2 * (p + 1)]


def fit_quality_model(
    X: np.ndarray, error_mm: np.ndarray, l1: float = 0.02, folds: int = 5, margin: float = 0.8
) -> QualityModel:
    """The quality model fitted to features X (n, n_features) and the true errors (n,) mm: the
    :data:`QUANTILES` of log error by :func:`quantile_regression`; the confidence bound set to ``margin``
    times the smallest upper quantile that any fit over :data:`BAD_MM` reached in ``folds``-fold
    out-of-fold predictions (and never above BAD_MM)."""
    X = np.asarray(X, np.float64)
    worst = np.where(np.array(list(FEATURES.values())), np.nanmax(X, 0), np.nanmin(X, 0))
    X = np.where(np.isfinite(X), X, worst)
    lo, hi = X.min(axis=0), X.max(axis=0)
    mean, scale = X.mean(axis=0), np.maximum(X.std(axis=0), 1e-6)
    y = np.log(np.asarray(error_mm, np.float64))

    def fitted(rows: np.ndarray) -> QualityModel:
        z = (X[rows] - mean) / scale
        coefficients = np.stack([quantile_regression(z, y[rows], tau, l1 * len(rows)) for tau in QUANTILES])
        return QualityModel(lo, hi, mean, scale, coefficients, BAD_MM)

    order = np.random.default_rng(0).permutation(len(y))
    upper = np.empty(len(y))
    for k in range(folds):
        held = order[k::folds]
        upper[held] = fitted(np.setdiff1d(order, held)).quantiles(X[held])[:, -1]
    bad = np.asarray(error_mm) > BAD_MM
    bound = min(BAD_MM, margin * float(upper[bad].min())) if bad.any() else BAD_MM
    full = fitted(np.arange(len(y)))
    return QualityModel(lo, hi, mean, scale, full.coefficients, bound)


def row_features(row: Mapping[str, Any], bind: np.ndarray, ranges: np.ndarray) -> np.ndarray:
    """:func:`scan_features` of a benchmark row (``scan_matrix.py``: its ``report``, ``mode``,
    ``coordinates`` and ``shape``; the prior distance and the mode are read from the row where the report
    lacks them)."""
    report = dict(row["report"])
    extra = dict(report.get("extra") or {})
    if "prior_distance" not in extra:
        extra["prior_distance"] = prior_distance(
            np.asarray(row["coordinates"]), np.asarray(row["shape"]), bind, ranges
        )
    extra.setdefault("orientation_searched", row.get("mode") != "hinted")
    report["extra"] = extra
    return scan_features(report)

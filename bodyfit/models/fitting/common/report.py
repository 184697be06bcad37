"""The error report every fit returns (what its fields mean for users: docs/fitting.md)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True)
class DistanceStats:
    """Distances in millimetres."""

    mean: float
    median: float
    p95: float
    max: float

    @classmethod
    def of(cls, metres: np.ndarray) -> DistanceStats:
        """Statistics of distances given in metres (any shape; NaN entries ignored)."""
        d = np.asarray(metres, np.float64).ravel() * 1000.0
        d = d[np.isfinite(d)]
        if d.size == 0:
            return cls(float("nan"), float("nan"), float("nan"), float("nan"))
        return cls(float(d.mean()), float(np.median(d)), float(np.percentile(d, 95)), float(d.max()))

    @classmethod
    def of_rows(cls, metres: np.ndarray, keep: np.ndarray) -> list[DistanceStats]:
        """One :meth:`of` per row of distances (k, N) metres, over the entries where ``keep`` (k, N) is
        true; all rows at once when every row keeps the same entries and they are finite."""
        columns = keep[0]
        chosen = np.asarray(metres)
        if not columns.all():
            chosen = chosen[:, columns]
        if (keep == columns).all() and np.isfinite(chosen).all() and chosen.shape[1] > 0:
            # in the distances' own float type (float32: sub-micrometre at this scale), then in mm
            mean, peak = chosen.mean(axis=1), chosen.max(axis=1)
            median, p95 = np.percentile(chosen, [50, 95], axis=1)
            rows = zip(mean, median, p95, peak, strict=True)
            return [cls(*(float(x) * 1000.0 for x in row)) for row in rows]
        return [cls.of(row[k]) for row, k in zip(metres, keep, strict=True)]

    @classmethod
    def weighted(cls, metres: np.ndarray, weights: np.ndarray) -> DistanceStats:
        """Statistics of distances (N,) in metres, each counted by its weight (N,) >= 0 (the surface area a
        mesh vertex stands for, so that dense parts of a mesh do not outweigh the rest): the weighted mean,
        median and 95th percentile (the smallest distance at or below which that share of the weight lies),
        and the maximum over entries of positive weight; NaN entries ignored."""
        d = np.asarray(metres, np.float64).ravel() * 1000.0
        w = np.asarray(weights, np.float64).ravel()
        keep = np.isfinite(d) & (w > 0)
        d, w = d[keep], w[keep]
        if d.size == 0:
            return cls(float("nan"), float("nan"), float("nan"), float("nan"))
        order = np.argsort(d)
        ranked, share = d[order], np.cumsum(w[order]) / w.sum()
        at = np.minimum(np.searchsorted(share, [0.5, 0.95]), d.size - 1)
        median, p95 = float(ranked[at[0]]), float(ranked[at[1]])
        return cls(float(np.average(d, weights=w)), median, p95, float(d.max()))


@dataclass(frozen=True)
class FitReport:
    """What a fit reports about itself.

    Attributes:
        distances: per-vertex / per-point / per-marker distances of the result to the input (mm).
        limit_violations: number of coordinate values outside their joint limits (always 0 when the fit
            worked; counted, not assumed).
        iterations: optimiser iterations over all stages.
        seconds: wall time of the fit.
        confident: False when the result should not be trusted; ``reasons`` says why.
        reasons: human-readable causes of low confidence (empty when confident).
        extra: fit-specific numbers (e.g. per-stage losses, scan coverage).
        scan_to_model: raw scans: every scan point's distance to the result's surface (mm), outliers
            included, so that ``max`` is the real maximum (``distances`` holds the inliers only); None for
            fits with a correspondence.
        model_to_scan: raw scans: each vertex of the result's surface to its nearest scan point (mm),
            weighted by the area the vertex stands for, over the part of the body the scan can show
            (``extra["model_to_scan_over"]``); None for fits with a correspondence.
        predicted_error_mm: raw scans: the registration's predicted mean distance to the true body (mm),
            calibrated on synthetic scans (:mod:`bodyfit.models.fitting.common.quality`); None where not
            estimated.
        predicted_error_interval_mm: the 10% and 90% quantiles of that prediction (mm); ``confident``
            needs the upper one below the calibrated bound.
    """

    distances: DistanceStats
    limit_violations: int
    iterations: int
    seconds: float
    confident: bool
    reasons: tuple[str, ...] = ()
    extra: dict[str, Any] = field(default_factory=dict)
    scan_to_model: DistanceStats | None = None
    model_to_scan: DistanceStats | None = None
    predicted_error_mm: float | None = None
    predicted_error_interval_mm: tuple[float, float] | None = None

    @classmethod
    def judged(
        cls,
        distances: DistanceStats,
        q: np.ndarray,
        ranges: np.ndarray,
        iterations: int,
        seconds: float,
        reasons: list[str],
        extra: dict[str, Any] | None = None,
        scan_to_model: DistanceStats | None = None,
        model_to_scan: DistanceStats | None = None,
        predicted: tuple[float, tuple[float, float]] | None = None,
    ) -> FitReport:
        """A report whose confidence follows from ``reasons`` (causes found by the fitter) plus the
        joint-limit violations of q (..., n_dof) against ``ranges`` (n_dof, 2), counted here; ``predicted``:
        the predicted error (mm) and its interval (mm), when estimated."""
        violations = count_limit_violations(q, ranges)
        if violations:
            reasons = [*reasons, f"{violations} coordinate values outside their joint limits"]
        return cls(
            distances,
            violations,
            iterations,
            seconds,
            not reasons,
            tuple(reasons),
            extra or {},
            scan_to_model,
            model_to_scan,
            None if predicted is None else predicted[0],
            None if predicted is None else predicted[1],
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (distances in mm)."""
        out = asdict(self)
        out["reasons"] = list(self.reasons)
        interval = self.predicted_error_interval_mm
        out["predicted_error_interval_mm"] = None if interval is None else list(interval)
        return out


def count_limit_violations(q: np.ndarray, ranges: np.ndarray, tolerance: float = 1e-9) -> int:
    """Number of entries of q (..., n_dof) outside ``ranges`` (n_dof, 2)."""
    q = np.asarray(q, np.float64)
    return int(((q < ranges[:, 0] - tolerance) | (q > ranges[:, 1] + tolerance)).sum())

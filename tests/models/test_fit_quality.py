"""A raw-scan fit's calibrated quality estimate: monotone in the evidence of a bad fit, confident with a small
predicted error on a fit that matches its scan, not confident on a raised arm fitted hanging, safe on
missing or broken features, and carried by the report through the wire models unchanged."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from bodyfit import wire as w
from bodyfit.io.scans import sample_surface
from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common import quality
from bodyfit.models.fitting.common.nearest import PointTree
from bodyfit.models.fitting.common.report import DistanceStats, FitReport
from bodyfit.models.fitting.common.surface import point_to_surface
from bodyfit.models.fitting.scan.config import ScanFitConfig
from bodyfit.models.fitting.scan.phases import clean_points
from bodyfit.models.fitting.scan.report import (
    MAX_UNEXPLAINED,
    ScanFit,
    both_ways,
    judge,
    seen_part,
    with_branch,
)


@pytest.fixture(scope="module")
def model() -> BodyModel:
    return BodyModel.load()


def _body(model: BodyModel, **degrees: float) -> tuple[np.ndarray, np.ndarray]:
    """The mean body's vertices (V, 3) and coordinates (n_dof,): the bind pose (inside the limits) with
    ``degrees`` set."""
    q = model.skeleton.inside(model.bind_coordinates, 0.1).copy()
    for name, value in degrees.items():
        q[model.skeleton.dof_index(name)] = np.radians(value)
    with torch.no_grad():
        out = model.forward(np.zeros((1, model.n_shape)), q[None], np.zeros((1, 3)), dtype=torch.float64)
    return out.vertices[0].numpy(), q


def _report(
    model: BodyModel, scan: np.ndarray, fitted: np.ndarray, q: np.ndarray, searched: bool
) -> FitReport:
    """The report of ``fitted`` (V, 3; coordinates q, the mean shape) on points sampled from ``scan``."""
    faces = np.asarray(model.faces, np.int64)
    points, _ = sample_surface(scan, faces, 12_000, seed=7)
    cfg = ScanFitConfig()
    cleaned = clean_points(points, cfg.voxel, cfg.neighbours, cfg.outlier_cutoff)
    distances = point_to_surface(points, fitted, faces)
    part, over = seen_part(fitted, faces, None, None)
    both = both_ways(points, distances, cleaned, fitted, faces, part, over)
    coverage = float(np.mean(PointTree(points).query(fitted)[0] < 0.02))  # vertices with a point near
    ranges = model.skeleton.ranges
    prior = quality.prior_distance(q, np.zeros(model.n_shape), model.bind_coordinates, ranges)
    losses = {"valley": 0.4}
    return judge(distances, coverage, 0.001, searched, None, q, ranges, 200, 5.0, losses, None, both, prior)


def test_the_estimate_grows_with_every_sign_of_a_bad_fit() -> None:
    m = quality.shipped_model()
    rng = np.random.default_rng(0)
    worse = np.array(list(quality.FEATURES.values()))
    assert worse.all()  # every feature is one where larger means worse
    for _ in range(20):
        base = m.lo + rng.uniform(0.0, 1.0, len(m.lo)) * (m.hi - m.lo)
        before = m.quantiles(base)
        for k in range(len(base)):
            bumped = base.copy()
            bumped[k] += 0.2 * (m.hi[k] - m.lo[k]) + 1e-6
            assert np.all(m.quantiles(bumped) >= before - 1e-9), list(quality.FEATURES)[k]
    low, mid, high = m.quantiles(m.lo)
    assert low <= mid <= high and m.quantiles(m.hi)[1] > 25.0  # the worst evidence predicts a gross error


@pytest.fixture(scope="module")
def matching(model: BodyModel) -> ScanFit:
    """A fit (orientation searched) that matches its scan: the scan sampled from the fitted body."""
    body, q = _body(model)
    z = np.zeros(3)
    return ScanFit(z, q, z, body, body, z, np.eye(4), z, _report(model, body, body, q, searched=True))


def test_a_fit_that_matches_its_scan_is_confident_with_a_small_predicted_error(matching: ScanFit) -> None:
    report = matching.report
    assert report.confident and report.reasons == ()
    assert report.predicted_error_mm is not None and report.predicted_error_mm < 10.0
    assert report.predicted_error_interval_mm is not None
    low, high = report.predicted_error_interval_mm
    assert low <= report.predicted_error_mm <= high < quality.shipped_model().confident_below_mm
    assert set(report.extra["prior_distance"]) == {"pose", "pinned", "shape"}


def test_a_raised_arm_fitted_hanging_is_not_confident(model: BodyModel) -> None:
    scan, _ = _body(model, arm_add_r=-110.0)
    fitted, q = _body(model, arm_add_r=-10.0)
    for searched in (True, False):
        report = _report(model, scan, fitted, q, searched)
        assert not report.confident and "not explained by the fit" in report.reasons[0]
        assert report.extra["unexplained_fraction"] > MAX_UNEXPLAINED
        assert report.predicted_error_interval_mm is not None  # predicted, yet not confident whatever it says
        hidden = _report(model, fitted, fitted, q, searched)  # the same fit, its scan without the raised arm
        assert hidden.confident


def test_branches_that_disagree_raise_the_estimate(matching: ScanFit) -> None:
    agree = with_branch(matching, 0, [0.40, 0.401]).report
    differ = with_branch(matching, 0, [0.40, 0.80]).report
    assert agree.predicted_error_mm is not None and differ.predicted_error_mm is not None
    assert differ.predicted_error_mm >= agree.predicted_error_mm
    assert agree.extra["branch_scores"] == [0.4, 0.401]


def test_missing_or_broken_features_are_not_trusted() -> None:
    m = quality.shipped_model()
    nothing = quality.scan_features({"distances": {"mean": "x"}, "extra": {"branch_scores": [0.0, -1.0]}})
    assert nothing.shape == (len(quality.FEATURES),) and np.isnan(nothing).any()
    prediction = m.predict(nothing)
    assert not prediction.confident and math.isfinite(prediction.error_mm)
    assert m.predict(np.full(len(quality.FEATURES), np.inf)).interval_mm == m.predict(m.hi).interval_mm
    wrong = {**m.to_json(), "features": ["something else"]}
    with pytest.raises(ValueError, match="other features"):
        quality.QualityModel.from_json(wrong)


def test_quantile_regression_finds_the_quantiles_and_keeps_the_weights_signs() -> None:
    rng = np.random.default_rng(1)
    x = rng.uniform(0.0, 1.0, 400)
    y = 2.0 * x + rng.uniform(0.0, 1.0, 400)  # the tau quantile at x is 2x + tau
    for tau in (0.1, 0.5, 0.9):
        b = quality.quantile_regression(x[:, None], y, tau)
        assert b == pytest.approx([tau, 2.0], abs=0.12)
    X = np.column_stack([x, rng.uniform(0.0, 1.0, (400, len(quality.FEATURES) - 1))])
    b = quality.quantile_regression(X, -3.0 * x, 0.5)  # falls with a feature marked worse-when-larger
    assert b[1] >= 0.0


def test_the_prediction_travels_through_the_wire_models_unchanged() -> None:
    stats = DistanceStats(1.0, 0.9, 2.5, 30.0)
    report = FitReport(stats, 0, 10, 1.5, False, ("why",), {"coverage": 0.9}, stats, stats, 12.5, (6.0, 31.0))
    doc = json.loads(json.dumps(report.to_dict()))
    read = w.FitReport.model_validate(doc)
    assert read.predicted_error_mm == 12.5 and read.predicted_error_interval_mm == (6.0, 31.0)
    assert json.loads(json.dumps(read.model_dump(mode="json"))) == doc
    bare = FitReport(stats, 0, 10, 1.5, True).to_dict()
    assert bare["predicted_error_mm"] is None and bare["predicted_error_interval_mm"] is None
    assert w.FitReport.model_validate(bare).model_dump(mode="json")["predicted_error_interval_mm"] is None

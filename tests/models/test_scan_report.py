"""A raw-scan fit's report reads its distances both ways: a limb of the scan that the fit left out, or a limb
fitted where the scan has nothing, shows in the real maximum, the unexplained share and the largest
unsupported region, and makes the fit not confident; a good fit of a scan with holes stays clear of both."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from bodyfit.io.scans import sample_surface
from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common.report import DistanceStats
from bodyfit.models.fitting.common.surface import point_to_surface
from bodyfit.models.fitting.scan.config import ScanFitConfig
from bodyfit.models.fitting.scan.phases import clean_points
from bodyfit.models.fitting.scan.report import (
    INLIER_MM,
    MAX_GAP,
    MAX_UNEXPLAINED,
    BothWays,
    both_ways,
    gap_parts,
    judge,
    part_name,
    seen_part,
)

ARM = ("humerus_r", "ulna_r", "radius_r", "hand_r")


@pytest.fixture(scope="module")
def model() -> BodyModel:
    return BodyModel.load()


def _body(model: BodyModel, **degrees: float) -> np.ndarray:
    """(V, 3) the mean body in the bind pose (moved inside the limits) with ``degrees`` set."""
    q = model.skeleton.inside(model.bind_coordinates, 0.1).copy()
    for name, value in degrees.items():
        q[model.skeleton.dof_index(name)] = np.radians(value)
    with torch.no_grad():
        out = model.forward(np.zeros((1, model.n_shape)), q[None], np.zeros((1, 3)), dtype=torch.float64)
    return out.vertices[0].numpy()


def _measure(model: BodyModel, points: np.ndarray, registration: np.ndarray) -> BothWays:
    faces = np.asarray(model.faces, np.int64)
    cfg = ScanFitConfig()
    cleaned = clean_points(points, cfg.voxel, cfg.neighbours, cfg.outlier_cutoff)
    distances = point_to_surface(points, registration, faces)
    part, over = seen_part(registration, faces, None, None)
    bodies = np.asarray(model.skeleton.body_names)[model.vertex_bodies]
    return both_ways(points, distances, cleaned, registration, faces, part, over, bodies)


def test_weighted_statistics_count_each_entry_by_its_weight() -> None:
    s = DistanceStats.weighted(np.array([0.001, 0.002, 0.010, np.nan]), np.array([1.0, 1.0, 2.0, 5.0]))
    assert s.mean == pytest.approx((1 + 2 + 2 * 10) / 4)
    assert (s.median, s.p95, s.max) == pytest.approx((2.0, 10.0, 10.0))
    unweighted = DistanceStats.weighted(np.array([0.004, 0.001]), np.array([0.0, 1.0]))
    assert unweighted.max == pytest.approx(1.0)  # an entry of no weight is not part of the statistics


def test_a_scan_limb_the_fit_left_out_shows_and_is_not_confident(model: BodyModel) -> None:
    """The scan's right arm is raised to 110 degrees, the fit's hangs down: about 92% of the points are
    inliers and their mean is small, so the inlier statistics alone look good."""
    faces = np.asarray(model.faces, np.int64)
    scan = _body(model, arm_add_r=-110.0)
    fitted = _body(model, arm_add_r=-10.0)
    points, _ = sample_surface(scan, faces, 40_000, seed=1)
    both = _measure(model, points, fitted)
    distances = point_to_surface(points, fitted, faces)
    inliers = DistanceStats.of(distances[distances * 1000 <= INLIER_MM])
    assert inliers.max <= INLIER_MM < 300.0 < both.scan_to_model.max
    assert both.unexplained > 3 * MAX_UNEXPLAINED and both.unexplained_mm > 300.0
    assert both.model_to_scan.max > 150.0 and both.largest_gap > MAX_GAP  # the hanging arm meets no points
    n_dof = model.skeleton.n_dof
    q = np.zeros(n_dof)
    ranges = np.tile([-1.0, 1.0], (n_dof, 1))
    report = judge(distances, 0.9, 0.0, False, None, q, ranges, 1, 1.0, {}, None, both)
    assert not report.confident and any("not explained by the fit" in r for r in report.reasons)
    assert report.distances.max <= INLIER_MM and report.scan_to_model is not None
    assert report.scan_to_model.max > 300.0
    doc = report.to_dict()
    assert doc["model_to_scan"]["max"] > 150.0 and doc["extra"]["model_to_scan_over"] == "whole body"
    assert doc["extra"]["unexplained_fraction"] > MAX_UNEXPLAINED


def test_a_limb_fitted_where_the_scan_has_nothing_is_not_confident(model: BodyModel) -> None:
    faces = np.asarray(model.faces, np.int64)
    fitted = _body(model)
    owner = np.array(model.skeleton.body_names)[np.argmax(model.data["weights"], axis=1)]
    without_arm = faces[~np.isin(owner[faces], ARM).any(axis=1)]
    points, _ = sample_surface(fitted, without_arm, 40_000, seed=2)
    both = _measure(model, points, fitted)
    assert both.unexplained == 0.0 and both.scan_to_model.max < 15.0  # every scan point is explained
    assert both.largest_gap > MAX_GAP and both.unsupported > MAX_GAP
    # the report names the parts of the body the scan has nothing of: the right arm's, away from the trunk
    assert both.gap_parts and set(both.gap_parts) <= {"right upper arm", "right forearm", "right hand"}
    assert both.extra()["largest_gap_parts"] == list(both.gap_parts)
    named = f"mostly the {both.gap_parts[0]}"
    assert any(named in r and "its pose is a guess" in r for r in both.reasons())


def test_a_region_is_named_by_the_parts_holding_a_fifth_of_its_area() -> None:
    assert [part_name(b) for b in ("humerus_l", "radius_r", "torso", "toes_r")] == [
        "left upper arm", "right forearm", "trunk", "right toes",
    ]  # fmt: skip
    bodies = np.array(["ulna_r", "radius_r", "hand_r", "humerus_r", "torso"])
    area = np.array([1.0, 2.0, 4.0, 0.5, 9.0])
    region = np.array([True, True, True, True, False])  # the trunk is outside the region
    # forearm (ulna and radius) 3/7.5, hand 4/7.5, upper arm 0.5/7.5 < 0.2: not named
    assert gap_parts(region, area, bodies) == ("right hand", "right forearm")


def test_a_good_fit_of_a_scan_with_holes_raises_no_reason(model: BodyModel) -> None:
    """Holes 10 cm across leave many small unsupported regions, not one limb-sized one."""
    faces = np.asarray(model.faces, np.int64)
    body = _body(model)
    points, _ = sample_surface(body, faces, 60_000, seed=3)
    rng = np.random.default_rng(3)
    centres = points[rng.choice(len(points), 25, replace=False)]
    near = np.linalg.norm(points[:, None] - centres[None], axis=2).min(axis=1) < 0.05
    both = _measure(model, points[~near], body)
    assert both.unsupported > 0.02  # the holes show in the share of the body without scan points ...
    assert both.largest_gap < MAX_GAP and both.unexplained == 0.0  # ... but not as a missing limb
    assert both.reasons() == [] and both.model_to_scan.p95 > both.model_to_scan.median


def test_a_single_view_is_measured_on_the_side_facing_its_sensor(model: BodyModel) -> None:
    faces = np.asarray(model.faces, np.int64)
    body = _body(model)
    front, name = seen_part(body, faces, np.array([1.0, 0.0, 0.0]), None)
    assert name == "the side of the whole body facing the sensor" and 0.2 < front.mean() < 0.6
    fitter_upper = np.flatnonzero(body[:, 1] > body[:, 1].max() - 0.4)
    upper, name = seen_part(body, faces, None, fitter_upper)
    assert name == "head and shoulders" and upper.sum() == len(fitter_upper)
    # a front view's points support the front and say nothing of the back
    seen_faces = faces[front[faces].all(axis=1)]
    points, _ = sample_surface(body, seen_faces, 30_000, seed=4)
    cfg = ScanFitConfig()
    both = both_ways(
        points,
        point_to_surface(points, body, faces),
        clean_points(points, cfg.voxel, cfg.neighbours, cfg.outlier_cutoff),
        body,
        faces,
        front,
        "front",
    )
    assert both.largest_gap < MAX_GAP and both.model_to_scan.p95 < 15.0

"""A scan fit's result (:class:`ScanFit`, :func:`placed_fit`): its parameters moved into the scan's frame
(:func:`in_scan_frame`) and its report, judged confident or not (:func:`judge`)."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common.nonrigid import refine_nonrigid
from bodyfit.models.fitting.common.report import DistanceStats, FitReport
from bodyfit.models.fitting.common.surface import point_to_surface
from bodyfit.models.fitting.scan.config import PART_NAMES, ScanFitConfig
from bodyfit.models.fitting.scan.hypotheses import HypothesisSteps
from bodyfit.models.fitting.scan.limb_search import Hypotheses
from bodyfit.models.fitting.scan.phases import PhaseRun
from bodyfit.models.rotations import zxy_angles

CONFIDENT_MEAN_MM = 10.0
MIN_INLIER_FRACTION = 0.85
MIN_COVERAGE = 0.5
INLIER_MM = 30.0  # scan points further than this from the registration count as outliers
COVERED_MM = 20.0  # a model vertex is covered when a scan point lies this close


@dataclass(frozen=True)
class ScanFit:
    """A fitted scan.

    shape (n_shape,), coordinates (n_dof,) in range, root (3,): the parameters, in the scan's frame unless
    ``scan_to_body`` is not the identity (then in the body frame ``body = scan_to_body @ scan``).
    vertices (V, 3): the parametric body in the scan's frame (metres); registration (V, 3): the non-rigid
    registration in our topology (equal to ``vertices`` without refinement); joints (J, 3) in the scan's
    frame. point_distances (N,): every scan point's distance to the registration surface (m).
    """

    shape: np.ndarray
    coordinates: np.ndarray
    root: np.ndarray
    vertices: np.ndarray
    registration: np.ndarray
    joints: np.ndarray
    scan_to_body: np.ndarray
    point_distances: np.ndarray
    report: FitReport


def in_scan_frame(
    model: BodyModel,
    pelvis: list[int],
    c: np.ndarray,
    q: np.ndarray,
    root: np.ndarray,
    rotation: np.ndarray,
    centre: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The coordinates (n_dof,) and root (3,) of a body (shape c, coordinates q, root (3,) in the body frame
    ``body = rotation @ (scan - centre)``), in the scan's frame when the pelvis angles (DOFs ``pelvis``) can
    hold its orientation, else as they are; the (4, 4) map from the scan's frame to theirs; the joints (J, 3)
    in the scan's frame."""
    skel = model.skeleton
    R, m = rotation, centre
    out = model.forward(c[None], q[None], root[None], dtype=torch.float64)
    frame = out.frames[0, 0].numpy()
    q_scan = q.copy()
    q_scan[pelvis] = zxy_angles(R.T @ frame[:3, :3])
    root_scan = R.T @ frame[:3, 3] + m
    inside = np.all((q_scan >= skel.ranges[:, 0] + 1e-6) & (q_scan <= skel.ranges[:, 1] - 1e-6))
    scan_to_body = np.eye(4)
    if inside:
        q, root = q_scan, root_scan
    else:
        scan_to_body[:3, :3], scan_to_body[:3, 3] = R, -R @ m
    joints = out.joints[0].numpy() @ R + m
    return q, root, scan_to_body, joints


def _reasons(
    fraction: float,
    mean_mm: float,
    coverage: float,
    partial_extent: float | None,
    view: np.ndarray | None,
    searched: bool,
) -> list[str]:
    """Why a fit is not confident (empty when it is): the lines of its report."""
    reasons = []
    if fraction < MIN_INLIER_FRACTION:
        reasons.append(
            f"only {fraction:.0%} of the scan's points lie within {INLIER_MM:.0f} mm of the fitted body: "
            "crop the background or other objects, or the scan may not be a human body"
        )
    if not mean_mm <= CONFIDENT_MEAN_MM:
        reasons.append(f"mean scan-to-body distance {mean_mm:.1f} mm exceeds {CONFIDENT_MEAN_MM:.0f} mm")
    if coverage < MIN_COVERAGE:
        reasons.append(
            f"the scan covers {coverage:.0%} of the body surface: the shape and pose of the rest are guesses"
        )
    if partial_extent is not None:
        reasons.append(
            f"the scan is {partial_extent:.2f} m across, less than a body: it was fitted as a head and "
            "shoulders; the rest of the body is the shape space's guess, in the start pose"
        )
    if view is not None:
        reasons.append(
            "the scan is one sensor's view: the side of the body it did not see is the model's guess"
        )
    if searched:
        reasons.append(
            "the orientation was searched: on varied poses such fits often match the surface with a "
            "wrong heading or wrong limbs, which the distances cannot show; pass orientation= (and a "
            "start pose) when you know them"
        )
    return reasons


def judge(
    distances: np.ndarray,
    coverage: float,
    offset: float,
    searched: bool,
    view: np.ndarray | None,
    q: np.ndarray,
    ranges: np.ndarray,
    iterations: int,
    seconds: float,
    losses: dict[str, float],
    partial_extent: float | None = None,
) -> FitReport:
    """The report of a fit: every scan point's distance (N,) to the registration, the share of the body's
    surface the scan covers, the non-rigid refinement's mean offset (m), whether the orientation was
    searched, a single view's direction (3,) or None, the coordinates (n_dof,) against their ``ranges``
    (n_dof, 2), the iterations, seconds and each phase's score, and ``partial_extent`` (m) when the scan
    was fitted as a head and shoulders."""
    inlier = distances * 1000.0 <= INLIER_MM
    stats = DistanceStats.of(distances[inlier])
    fraction = float(inlier.mean())
    reasons = _reasons(fraction, stats.mean, coverage, partial_extent, view, searched)
    extra = {
        "inlier_fraction": round(fraction, 4),
        "inlier_threshold_mm": INLIER_MM,
        "coverage": round(coverage, 4),
        "single_view": None if view is None else [round(float(x), 4) for x in view],
        "nonrigid_offset_mm": round(offset * 1000, 2),
        "phase_scores": {k: round(v, 5) for k, v in losses.items()},
        "fitted_part": PART_NAMES["all" if partial_extent is None else "upper"],
    }
    return FitReport.judged(stats, q, ranges, iterations, seconds, reasons, extra)


def placed_fit(
    steps: HypothesisSteps,
    config: ScanFitConfig,
    hyp: Hypotheses,
    points: np.ndarray,
    run: PhaseRun,
    iterations: int,
    losses: dict[str, float],
    start: float,
    partial_extent: float | None = None,
) -> ScanFit:
    """The fit of the best hypothesis of ``hyp``: refined (``config.nonrigid``), in the scan's frame, with
    every raw point's (N, 3) distance to the registration (in ``config.workers`` parts, on the run's
    threads) and the report (``start``: when the fit began, ``time.perf_counter``; ``partial_extent``: the
    scan's largest extent (m) when it was fitted as a head and shoulders)."""
    model, faces = steps.model, steps.faces
    R, m = hyp.rotation[0], hyp.centre
    c, q, root = (t[0].numpy() for t in steps.fitter.parameters(hyp.state))
    all_verts = steps.vertices(hyp.state)
    body_verts = all_verts[0]
    body_points = (run.cleaned - m) @ R.T
    registration = body_verts
    if config.nonrigid is not None:
        # a single view's side facing its sensor
        seen = steps.visible(hyp, np.arange(model.n_vertices), all_verts)
        registration = refine_nonrigid(
            body_verts,
            faces,
            body_points,
            config.nonrigid,
            seen=None if seen is None else seen[0],
        )
    q, root, scan_to_body, joints = in_scan_frame(model, steps.pelvis, c, q, root, R, m)
    vertices = body_verts @ R + m
    registration = registration @ R + m
    parts = np.array_split(points, config.workers)
    distances = np.concatenate(
        list(run.pool.map(lambda part: point_to_surface(part, registration, faces), parts))
    )
    offset = float(np.linalg.norm(registration - vertices, axis=1).mean())
    coverage = float(np.mean(run.tree.query(registration, COVERED_MM / 1000)[0] < np.inf))
    seconds = time.perf_counter() - start
    ranges = model.skeleton.ranges
    report = judge(
        distances,
        coverage,
        offset,
        hyp.searched,
        hyp.view,
        q,
        ranges,
        iterations,
        seconds,
        losses,
        partial_extent,
    )
    return ScanFit(c, q, root, vertices, registration, joints, scan_to_body, distances, report)


def with_branch(fit: ScanFit, best: int, scores: list[float]) -> ScanFit:
    """``fit`` with its report saying which branch it came from (``best``) and each branch's score."""
    extra = {
        **fit.report.extra,
        "branch": best,
        "branch_scores": [round(x, 5) for x in scores],
    }
    return replace(fit, report=replace(fit.report, extra=extra))

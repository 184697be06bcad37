"""A scan fit's result (:class:`ScanFit`, :func:`placed_fit`): its parameters moved into the scan's frame
(:func:`in_scan_frame`), its distances both ways (:func:`both_ways`: scan to model and model to scan) and its
report, judged confident or not by its calibrated predicted error (:func:`judge`, :func:`assessed`)."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
import torch
from scipy import sparse
from scipy.sparse.csgraph import connected_components

from bodyfit.models.body.model import BodyDecoder, BodyModel
from bodyfit.models.fitting.common.nearest import PointTree
from bodyfit.models.fitting.common.nonrigid import refine_nonrigid
from bodyfit.models.fitting.common.quality import Prediction, prior_distance, scan_features, shipped_model
from bodyfit.models.fitting.common.report import DistanceStats, FitReport
from bodyfit.models.fitting.common.surface import point_to_surface, vertex_normals
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
# A cleaned scan point (isolated points dropped, one per 1 cm cell: about evenly spread over the surface)
# this far from the registration is unexplained. On the quick scan benchmark's good fits at most 0.24% of the
# cleaned scan is (clothing); a raised arm fitted hanging down leaves about 7%, a hand about 1%.
UNEXPLAINED_MM = 50.0
MAX_UNEXPLAINED = 0.01
UNSUPPORTED_MM = 30.0  # reported: the share of the body's surface this far from every scan point
# A connected region of the body's surface this far from every scan point, larger than MAX_GAP of it, is a
# limb fitted where the scan has nothing: an arm is about 5% of the surface, while the 10 cm holes of the
# scan benchmark leave regions of at most 1.3% (regions, not the total: holes are many small ones).
GAP_MM = 80.0
MAX_GAP = 0.03
# The skeleton's bodies as a report names them: the parts of the largest such region (:func:`gap_parts`).
BODY_NAMES = {
    "pelvis": "pelvis", "torso": "trunk", "thorax": "trunk", "head": "head", "scapula": "shoulder",
    "femur": "thigh", "patella": "knee", "tibia": "lower leg", "talus": "foot", "calcn": "foot",
    "toes": "toes", "humerus": "upper arm", "ulna": "forearm", "radius": "forearm", "hand": "hand",
}  # fmt: skip
MIN_PART_SHARE = 0.2  # of the region's area: a part holding less is not named
# A vertex of a single view's fit counts as seen when its normal turns this far towards the sensor: the
# grazing band at the silhouette, where a depth camera returns few points, is left out.
FACING_COS = 0.2
PREDICTED = "predicted registration error"  # how the reason that states the prediction begins


@dataclass(frozen=True)
class ScanFit:
    """A fitted scan.

    shape (n_shape,), coordinates (n_dof,) in range, root (3,): the parameters, in the scan's frame unless
    ``scan_to_body`` is not the identity (then in the body frame ``body = scan_to_body @ scan``).
    vertices (V, 3): the parametric body in the scan's frame (metres); registration (V, 3): the non-rigid
    registration in our topology (equal to ``vertices`` without refinement); joints (J, 3) in the scan's
    frame. point_distances (N,): the distance to the registration surface (m) of every scan point the scene
    separation kept as the person's (all of them when it is off or removed nothing).
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
    decoder: BodyDecoder | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The coordinates (n_dof,) and root (3,) of a body (shape c, coordinates q, root (3,) in the body frame
    ``body = rotation @ (scan - centre)``), in the scan's frame when the pelvis angles (DOFs ``pelvis``) can
    hold its orientation, else as they are; the (4, 4) map from the scan's frame to theirs; the joints (J, 3)
    in the scan's frame. ``decoder``: a known person's float64 decoder (their joints), else the model's."""
    skel = model.skeleton
    R, m = rotation, centre
    if decoder is None:
        out = model.forward(c[None], q[None], root[None], dtype=torch.float64)
        frames, joint_rows = out.frames, out.joints
    else:
        with torch.no_grad():
            args = (torch.as_tensor(a[None], dtype=torch.float64) for a in (c, q, root))
            _, joint_rows, frames, _ = decoder(*args)
    frame = frames[0, 0].numpy()
    q_scan = q.copy()
    q_scan[pelvis] = zxy_angles(R.T @ frame[:3, :3])
    root_scan = R.T @ frame[:3, 3] + m
    inside = np.all((q_scan >= skel.ranges[:, 0] + 1e-6) & (q_scan <= skel.ranges[:, 1] - 1e-6))
    scan_to_body = np.eye(4)
    if inside:
        q, root = q_scan, root_scan
    else:
        scan_to_body[:3, :3], scan_to_body[:3, 3] = R, -R @ m
    joints = joint_rows[0].numpy() @ R + m
    return q, root, scan_to_body, joints


@dataclass(frozen=True)
class BothWays:
    """A fit's distances both ways (see :func:`both_ways`).

    scan_to_model: every scan point to the registration's surface (outliers included: the real maximum);
    unexplained: the share of the cleaned scan farther than :data:`UNEXPLAINED_MM`, and ``unexplained_mm``
    the farthest of those (0 when none); model_to_scan: each registration vertex to its nearest scan point,
    weighted by area, over the part ``over`` names; unsupported: the share of that part's area farther than
    :data:`UNSUPPORTED_MM`; largest_gap: the share of the largest connected region farther than
    :data:`GAP_MM`, and gap_parts the parts of the body it lies on (:func:`gap_parts`; empty when the
    vertices' bodies were not given).
    """

    scan_to_model: DistanceStats
    unexplained: float
    unexplained_mm: float
    model_to_scan: DistanceStats
    unsupported: float
    largest_gap: float
    over: str
    gap_parts: tuple[str, ...] = ()

    def extra(self) -> dict[str, object]:
        """The report's ``extra`` entries."""
        return {
            "unexplained_fraction": round(self.unexplained, 4),
            "unexplained_threshold_mm": UNEXPLAINED_MM,
            "unsupported_fraction": round(self.unsupported, 4),
            "unsupported_threshold_mm": UNSUPPORTED_MM,
            "largest_gap_fraction": round(self.largest_gap, 4),
            "gap_threshold_mm": GAP_MM,
            "largest_gap_parts": list(self.gap_parts),
            "model_to_scan_over": self.over,
        }

    def hard_reasons(self) -> list[str]:
        """Why these distances make a fit not confident whatever its predicted error: a part of the scan
        left unexplained (over :data:`MAX_UNEXPLAINED` of it). No good fit of the calibration matrix leaves
        more than 0.9% unexplained, while most fits over 25 mm off do (19 of 28), and the quantile
        regressions, fitted where few bad fits show it, do not weigh it enough alone."""
        if self.unexplained <= MAX_UNEXPLAINED:
            return []
        return [
            f"{self.unexplained:.1%} of the scan (isolated points left out) lies more than "
            f"{UNEXPLAINED_MM:.0f} mm from the fitted body, up to {self.unexplained_mm:.0f} mm: a "
            "part of the scan, such as a raised arm, is not explained by the fit (or an object beside "
            "the person was kept)"
        ]

    def reasons(self) -> list[str]:
        """What in these distances raises a fit's predicted error: a region of the body fitted where the
        scan has nothing."""
        out = []
        if self.largest_gap > MAX_GAP:
            where = f", mostly the {_listed(self.gap_parts)}," if self.gap_parts else ""
            out.append(
                f"a connected {self.largest_gap:.1%} of the fitted body's surface ({self.over}){where} lies "
                f"more than {GAP_MM:.0f} mm from every scan point: a limb is fitted where the scan has "
                "nothing, and its pose is a guess"
            )
        return out


def _listed(names: tuple[str, ...]) -> str:
    """'a', 'a and b', 'a, b and c'."""
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} and {names[-1]}"


def part_name(body: str) -> str:
    """A skeleton body's name as a report gives it: "humerus_l" -> "left upper arm"."""
    base, _, side = body.rpartition("_")
    if side in ("r", "l") and base:
        return f"{'right' if side == 'r' else 'left'} {BODY_NAMES.get(base, base)}"
    return BODY_NAMES.get(body, body)


def gap_parts(region: np.ndarray, area: np.ndarray, bodies: np.ndarray) -> tuple[str, ...]:
    """The parts of the body (:func:`part_name`) that hold at least :data:`MIN_PART_SHARE` of the area of a
    ``region`` (V,) bool of the surface, largest first: ``area`` (V,) each vertex's, ``bodies`` (V,) the
    skeleton body each vertex belongs to."""
    names = np.array([part_name(str(b)) for b in bodies[region]])
    parts, index = np.unique(names, return_inverse=True)
    share = np.bincount(index, area[region]) / max(float(area[region].sum()), 1e-12)
    order = np.argsort(-share)
    return tuple(str(parts[k]) for k in order if share[k] >= MIN_PART_SHARE)


def vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V,) the area each vertex of a mesh (V, 3), (F, 3) stands for: a third of each face's around it."""
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return np.bincount(faces.ravel(), np.repeat(area / 3.0, 3), minlength=len(vertices))


def largest_region(mask: np.ndarray, weights: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V,) bool: the heaviest (summed ``weights`` (V,)) region of vertices ``mask`` (V,) connected by the
    edges of ``faces`` (F, 3) among themselves; all False when ``mask`` is."""
    if not mask.any():
        return mask.copy()
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges = edges[mask[edges].all(axis=1)]
    n = len(mask)
    graph = sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    heaviest = int(np.argmax(np.bincount(label[mask], weights[mask])))
    return mask & (label == heaviest)


def seen_part(
    registration: np.ndarray, faces: np.ndarray, view: np.ndarray | None, fitted: np.ndarray | None
) -> tuple[np.ndarray, str]:
    """(V,) the vertices of a registration (V, 3) the scan can show, and their name in reports: those facing a
    single view's sensor (``view`` (3,) towards it, scan frame, or None for a full scan) among the
    ``fitted`` vertices (indices of a head-and-shoulders fit, or None for the whole body)."""
    part = np.ones(len(registration), bool)
    name = "whole body"
    if fitted is not None:
        part[:] = False
        part[fitted] = True
        name = "head and shoulders"
    if view is not None:
        part &= vertex_normals(registration, faces) @ np.asarray(view, np.float64) > FACING_COS
        name = f"the side of the {name} facing the sensor"
    return part, name


def both_ways(
    points: np.ndarray,
    distances: np.ndarray,
    cleaned: np.ndarray,
    registration: np.ndarray,
    faces: np.ndarray,
    part: np.ndarray,
    over: str,
    bodies: np.ndarray | None = None,
) -> BothWays:
    """A fit's distances both ways: scan points (N, 3) with their ``distances`` (N,) to the registration's
    surface (V, 3), (F, 3); the cleaned scan (M, 3) (isolated points dropped: stray points do not count as
    unexplained, an unexplained limb does); the registration's vertices ``part`` (V,) bool the scan can show
    (:func:`seen_part`), named ``over``; ``bodies`` (V,): each vertex's skeleton body, to name the parts of
    the largest unsupported region. Model to scan is point to point: each vertex's nearest scan point.

    The two-way Chamfer distance (H. G. Barrow, J. M. Tenenbaum, R. C. Bolles and H. C. Wolf, "Parametric
    correspondence and chamfer matching: Two new techniques for image matching", International Joint
    Conference on Artificial Intelligence (IJCAI), 1977), read one way at a time: a scan limb the fit left
    out shows in the first, a limb fitted where the scan has nothing in the second.
    """
    tree = PointTree(points)
    to_scan, _ = tree.query(registration)
    _, nearest = tree.query(cleaned)  # the cleaned points are scan points: their own distances
    cleaned_d = distances[nearest]
    far = cleaned_d * 1000.0 > UNEXPLAINED_MM
    area = vertex_areas(registration, faces) * part
    total = max(float(area.sum()), 1e-12)
    gap = largest_region(part & (to_scan * 1000.0 > GAP_MM), area, faces)
    return BothWays(
        scan_to_model=DistanceStats.of(distances),
        unexplained=float(far.mean()) if len(far) else 0.0,
        unexplained_mm=float(cleaned_d[far].max() * 1000.0) if far.any() else 0.0,
        model_to_scan=DistanceStats.weighted(to_scan, area),
        unsupported=float(area[to_scan * 1000.0 > UNSUPPORTED_MM].sum() / total),
        largest_gap=float(area[gap].sum()) / total,
        over=over,
        gap_parts=() if bodies is None or not gap.any() else gap_parts(gap, area, bodies),
    )


def _hard_reasons(fraction: float, partial_extent: float | None, view: np.ndarray | None) -> list[str]:
    """Causes that make a fit not confident whatever its predicted error: too few inliers (the scan may hold
    more than one body, or none), a head and shoulders fitted in place of a body, or one sensor's view (and,
    from the distances both ways, :meth:`BothWays.hard_reasons`). A single view leaves the far side of the
    body and any limb behind it unseen: on the quick confidence matrix a walking body's left foot was
    fitted 24 cm from its place (26.5 mm mean over the body) while every distance to the view looked good,
    so no prediction from those distances can vouch for it."""
    reasons = []
    if fraction < MIN_INLIER_FRACTION:
        reasons.append(
            f"only {fraction:.0%} of the scan's points lie within {INLIER_MM:.0f} mm of the fitted body: "
            "crop the background or other objects, or the scan may not be a human body"
        )
    if view is not None:
        reasons.append(
            "the scan is one sensor's view: the side of the body it did not see, and any limb hidden behind "
            "the body, are the model's guess"
        )
    if partial_extent is not None:
        reasons.append(
            f"the scan is {partial_extent:.2f} m across, less than a body: it was fitted as a head and "
            "shoulders; the rest of the body is the shape space's guess, in the start pose"
        )
    return reasons


def _observations(mean_mm: float, coverage: float, searched: bool, both: BothWays | None) -> list[str]:
    """What in a fit's distances and circumstances can make its predicted error large: the report's
    ``extra["observations"]``, and its reasons when the prediction is not confident."""
    out = []
    if not mean_mm <= CONFIDENT_MEAN_MM:
        out.append(f"mean scan-to-body distance {mean_mm:.1f} mm exceeds {CONFIDENT_MEAN_MM:.0f} mm")
    if coverage < MIN_COVERAGE:
        out.append(
            f"the scan covers {coverage:.0%} of the body surface: the shape and pose of the rest are guesses"
        )
    if both is not None:
        out += both.reasons()
    if searched:
        out.append(
            "the orientation was searched: give the scan's up axis and facing when you know them (up= and "
            "facing=, e.g. up=+y facing=+z, on REST, gRPC and the SDK; --up and --facing on the command "
            "line; ScanFitter.fit(orientation=)), and its pose class (pose=, --pose: standing, sitting, "
            "a-pose or t-pose)"
        )
    return out


def _prediction(report: FitReport) -> Prediction | None:
    """The calibrated prediction of a raw-scan fit's registration error (:mod:`.common.quality`), or None
    when the shipped model cannot be read."""
    try:
        model = shipped_model()
    except (OSError, ValueError, KeyError):
        return None
    return model.predict(scan_features(report.to_dict()))


def assessed(report: FitReport) -> FitReport:
    """``report`` with its predicted error, interval and confidence from its current entries: confident
    when the prediction is (its interval's upper end below the calibrated bound) and no hard reason (joint
    limits, too few inliers, a head-and-shoulders fit) stands; when it is not, the reasons say what the
    prediction is and what in the fit leads to it (``extra["observations"]``)."""
    observations = list(report.extra.get("observations", []))
    hard = [r for r in report.reasons if r not in observations and not r.startswith(PREDICTED)]
    prediction = _prediction(report)
    if prediction is None:
        reasons = hard + observations
        return replace(report, confident=not reasons, reasons=tuple(reasons))
    low, high = prediction.interval_mm
    reasons = list(hard)
    if not prediction.confident:
        bound = shipped_model().confident_below_mm
        reasons += [
            f"{PREDICTED} {prediction.error_mm:.0f} mm (80% interval {low:.0f}-{high:.0f} mm): the "
            f"interval's upper end is not below {bound:.0f} mm",
            *observations,
        ]
    return replace(
        report,
        confident=not reasons,
        reasons=tuple(reasons),
        predicted_error_mm=round(prediction.error_mm, 2),
        predicted_error_interval_mm=(round(low, 2), round(high, 2)),
    )


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
    both: BothWays | None = None,
    prior: dict[str, float] | None = None,
) -> FitReport:
    """The report of a fit: every scan point's distance (N,) to the registration, the share of the body's
    surface the scan covers, the non-rigid refinement's mean offset (m), whether the orientation was
    searched, a single view's direction (3,) or None, the coordinates (n_dof,) against their ``ranges``
    (n_dof, 2), the iterations, seconds and each phase's score, ``partial_extent`` (m) when the scan
    was fitted as a head and shoulders, the distances both ways (:func:`both_ways`) when measured, and the
    pose's and shape's distance from the prior (:func:`.common.quality.prior_distance`). ``distances`` in
    the report are the inliers' (within :data:`INLIER_MM`); ``scan_to_model`` all points'. Its confidence
    and predicted error: :func:`assessed`."""
    inlier = distances * 1000.0 <= INLIER_MM
    stats = DistanceStats.of(distances[inlier])
    fraction = float(inlier.mean())
    hard = _hard_reasons(fraction, partial_extent, view) + ([] if both is None else both.hard_reasons())
    extra = {
        "inlier_fraction": round(fraction, 4),
        "inlier_threshold_mm": INLIER_MM,
        "coverage": round(coverage, 4),
        "single_view": None if view is None else [round(float(x), 4) for x in view],
        "nonrigid_offset_mm": round(offset * 1000, 2),
        "phase_scores": {k: round(v, 5) for k, v in losses.items()},
        "fitted_part": PART_NAMES["all" if partial_extent is None else "upper"],
        "orientation_searched": searched,
        **({} if both is None else both.extra()),
        **({} if prior is None else {"prior_distance": prior}),
        "observations": _observations(stats.mean, coverage, searched, both),
    }
    if both is None:
        report = FitReport.judged(stats, q, ranges, iterations, seconds, hard, extra)
    else:
        report = FitReport.judged(
            stats, q, ranges, iterations, seconds, hard, extra, both.scan_to_model, both.model_to_scan
        )
    return assessed(report)


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
    body = steps.fitter.body
    decoder = None if body is None else body.decoder(torch.float64)
    q, root, scan_to_body, joints = in_scan_frame(model, steps.pelvis, c, q, root, R, m, decoder)
    vertices = body_verts @ R + m
    registration = registration @ R + m
    parts = np.array_split(points, config.workers)
    distances = np.concatenate(
        list(run.pool.map(lambda part: point_to_surface(part, registration, faces), parts))
    )
    offset = float(np.linalg.norm(registration - vertices, axis=1).mean())
    coverage = float(np.mean(run.tree.query(registration, COVERED_MM / 1000)[0] < np.inf))
    fitted = None if partial_extent is None else steps.fitter.index["upper"]
    part, over = seen_part(registration, faces, hyp.view, fitted)
    bodies = np.asarray(model.skeleton.body_names)[model.vertex_bodies]
    both = both_ways(points, distances, run.cleaned, registration, faces, part, over, bodies)
    seconds = time.perf_counter() - start
    ranges = model.skeleton.ranges
    prior = prior_distance(q, c, model.bind_coordinates, ranges)
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
        both,
        prior,
    )
    return ScanFit(c, q, root, vertices, registration, joints, scan_to_body, distances, report)


def with_branch(fit: ScanFit, best: int, scores: list[float]) -> ScanFit:
    """``fit`` with its report saying which branch it came from (``best``) and each branch's score, and
    assessed again (:func:`assessed`): branches that disagree make the prediction less certain."""
    extra = {
        **fit.report.extra,
        "branch": best,
        "branch_scores": [round(x, 5) for x in scores],
    }
    return replace(fit, report=assessed(replace(fit.report, extra=extra)))

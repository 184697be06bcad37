"""Motion capture markers -> our skeleton's coordinates, per frame, within the joint limits.

``fit_markers(trial, static)`` is the public entry point:

1. pick the marker protocol (:mod:`.marker_sets`: OpenSim gait2392 or Rajagopal2015, or by name overlap)
   and put its virtual markers on our template (:func:`.calibration.virtual_markers`);
2. calibrate the subject (:mod:`.subject`): from the static trial (after :mod:`.static_check` has made
   sure it shows the motion's markers on the same subject: scales and standing pose from the anatomical
   markers, every marker placed where the static trial saw it, as OpenSim's ScaleTool and MarkerPlacer do,
   then the technical and upper-body markers refined on frames of the motion) and from K frames of the
   motion itself (scales, technical marker locations and those frames' poses together); with a static
   trial both are fitted, compared on the motion and one kept (:mod:`.choice`);
3. inverse kinematics of all frames at once (:mod:`.marker_solve`), the coordinates the markers cannot
   determine held near neutral (:mod:`.observability`);
4. an error report (:class:`~bodyfit.models.fitting.common.report.FitReport`): marker distances,
   joint-limit violations, iterations, time, and confidence with reasons.

Steps 2 and 3 follow OpenSim's scaling, marker placement and inverse kinematics (S. L. Delp et al., "OpenSim:
Open-Source Software to Create and Analyze Dynamic Simulations of Movement", IEEE Transactions on Biomedical
Engineering 54(11), 2007; A. Seth et al., "OpenSim: Simulating musculoskeletal dynamics and neuromuscular
control to study human and animal movement", PLoS Computational Biology 14(7), 2018). User guide:
docs/fitting.md.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from bodyfit.io.mocap import MarkerTrial
from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common.report import DistanceStats, FitReport
from bodyfit.models.fitting.mocap.calibration import (
    SCALE_SIGMA,
    DofPlan,
    ScaleModel,
    VirtualMarkers,
    moved_bodies,
    place_markers,
    virtual_markers,
)
from bodyfit.models.fitting.mocap.choice import choice_report, choose_calibration
from bodyfit.models.fitting.mocap.marker_sets import (
    MarkerSetError,
    MarkerSetName,
    choose_marker_set,
    normalise_name,
)
from bodyfit.models.fitting.mocap.marker_solve import IKSolution, solve_ik
from bodyfit.models.fitting.mocap.observability import at_limits, holding_neutral, unobservable
from bodyfit.models.fitting.mocap.static_check import check_static
from bodyfit.models.fitting.mocap.subject import Calibration, calibrate
from bodyfit.models.skeleton.model import Skeleton
from bodyfit.models.skeleton.opensim_export import write_mot, write_osim
from bodyfit.models.skeleton.spec import SkeletonSpec

MIN_VISIBLE = 6  # markers a frame needs for a trustworthy pose
MAX_MEAN_ERROR = 0.02  # m: a mean marker error above this makes the fit not confident
CALIBRATION_FRAMES = 24  # frames of the motion used when there is no static trial
REFINE_SCALE_SIGMA = 0.02  # log-scale prior about the static trial's scales when refining on the motion
LOWER_BODIES = ("pelvis", "femur", "tibia", "patella", "talus", "calcn", "toes")  # static-placed anatomy
ARM_BODIES = ("scapula", "humerus", "ulna", "radius", "hand")  # their anatomical markers stay at defaults
CalibrationMode = Literal["auto", "static", "motion"]
"""How :func:`fit_markers` calibrates the subject: from the static trial, from the motion, or ``"auto"``."""


@dataclass(frozen=True)
class MarkerFit:
    """The result of :func:`fit_markers`.

    Attributes:
        coordinates: (T, n_dof) radians / metres in ``dof_names`` order, inside the joint limits.
        root: (T, 3) pelvis translation (m). times: (T,) s.
        scales: (n_seg, 3) segment scale factors of the subject.
        markers: the calibrated virtual markers (body-frame locations before scaling).
        marker_errors: (T, M) distance of each model marker to its measurement (m; NaN where missing),
            markers in ``markers.names`` order.
        static_coordinates: (n_dof,) the standing pose of the static trial, or None.
        marker_set: the protocol used. dof_names: coordinate names. report: the error report.
    """

    coordinates: np.ndarray
    root: np.ndarray
    times: np.ndarray
    scales: np.ndarray
    markers: VirtualMarkers
    marker_errors: np.ndarray
    static_coordinates: np.ndarray | None
    marker_set: str
    dof_names: list[str]
    report: FitReport

    def write(self, folder: str | Path, spec: SkeletonSpec, name: str = "subject") -> dict[str, Path]:
        """Write ``<name>.osim`` (scaled skeleton with the calibrated MarkerSet) and ``<name>.mot``."""
        out = Path(folder)
        out.mkdir(parents=True, exist_ok=True)
        marker_rows = list(zip(self.markers.names, self.markers.bodies, self.markers.local))
        osim = write_osim(out / f"{name}.osim", spec, self.scales, name, marker_rows)
        rate = 1.0 / float(np.median(np.diff(self.times))) if len(self.times) > 1 else 60.0
        mot = write_mot(out / f"{name}.mot", spec, self.coordinates, self.root, self.times, rate, name)
        return {"osim": osim, "mot": mot}


def observed_positions(trial: MarkerTrial, names: list[str]) -> np.ndarray:
    """Positions (T, M, 3) of the markers ``names`` (set names; trial names are matched after
    :func:`~.marker_sets.normalise_name`) in a trial, NaN for markers it does not have."""
    index = {normalise_name(n): i for i, n in enumerate(trial.names)}
    out = np.full((trial.n_frames, len(names), 3), np.nan)
    for k, n in enumerate(names):
        if n in index:
            out[:, k] = trial.positions[:, index[n]]
    return out


def _calibration_frames(observed: np.ndarray, count: int) -> np.ndarray:
    """Up to ``count`` frames spread evenly over the trial, among those showing the most markers."""
    seen = np.isfinite(observed).all(-1).sum(-1)
    good = np.flatnonzero(seen >= seen.max() - 2)
    return good[np.unique(np.linspace(0, len(good) - 1, min(count, len(good))).round().astype(int))]


def fit_markers(
    trial: MarkerTrial,
    static: MarkerTrial | None = None,
    marker_set: MarkerSetName = "auto",
    *,
    model: BodyModel | None = None,
    weights: Mapping[str, float] | None = None,
    static_window: tuple[float, float] | None = None,
    static_pose: Mapping[str, float] | None = None,
    calibration: CalibrationMode = "auto",
    calibration_frames: int = CALIBRATION_FRAMES,
    max_iterations: int = 50,
) -> MarkerFit:
    """Coordinates of our skeleton for every frame of a marker trial, with subject calibration.

    Args:
        trial: the motion (:func:`~bodyfit.io.mocap.read_markers`), positions in our world frame.
        static: a standing trial of the same subject with the same markers (plus any static-only
            anatomical ones, e.g. knee and ankle markers), or None to calibrate from the motion.
        marker_set: ``"auto"`` (the set sharing most names with the motion), ``"gait2392"`` or
            ``"rajagopal"``.
        model: the body model (loaded when None).
        weights: IK weight overrides by marker name (0 drops a marker).
        static_window: (start, stop) seconds of the static trial to average (default: all of it).
        static_pose: coordinates (name -> rad or m) held at these values in the static trial's standing
            pose, as a lab's OpenSim ScaleTool setup holds them with its coordinate tasks (e.g. the ankles
            at 0 for a subject standing in shoes): the markers placed in that pose set the zero of those
            coordinates in the motion. Default: the pose fitted to the markers.
        calibration: ``"static"``: from the static trial (scales, standing pose and every marker it shows;
            the technical and upper-body markers then refined on frames of the motion); ``"motion"``: from
            frames of the motion (scales and technical marker locations; with a static trial and
            ``static_pose`` the markers on the bodies the held coordinates move are then placed where the
            static trial saw them); ``"auto"``: with a static trial both are fitted and compared on the
            motion, the static one kept unless its mean marker error is more than
            :data:`~.choice.STATIC_TOLERANCE` times the motion one's (:mod:`.choice`); without one,
            "motion". The comparison is in ``report.extra["calibration_choice"]`` whenever a static trial
            is given.
        calibration_frames: frames of the motion used for calibration.
        max_iterations: Levenberg-Marquardt iterations per frame and pass.
    Returns:
        :class:`MarkerFit`; ``report.extra["unobservable"]`` names the coordinates the markers cannot
        determine (held near 0, :mod:`.observability`) with the reason.
    Raises:
        MarkerSetError: unknown set, too few shared markers, or a static trial from another marker protocol
            or another subject (:mod:`.static_check`). ShapeError/ValueError: bad inputs.
        UnknownCoordinateError: a ``static_pose`` name that is not a coordinate.
    """
    t0 = time.perf_counter()
    if trial.n_frames == 0:
        raise MarkerSetError("the trial has no frames")
    mode = _calibration_mode(calibration, static, static_pose)
    model = model or BodyModel.load()
    skel = model.skeleton
    defn = choose_marker_set(trial.names, marker_set)
    window = None if static is None else static if static_window is None else static.between(*static_window)
    check = None if window is None else check_static(trial, window, defn)
    plan = DofPlan.build(skel, defn)
    setup = _Setup(
        skel, ScaleModel(model), _weighted(virtual_markers(defn, model), weights, defn.name), defn.name,
        plan, plan.holding(skel, static_pose) if static_pose else plan, trial, window, static_pose,
        calibration_frames, max_iterations, defn.calibration_held,
    )  # fmt: skip
    kinds = ["motion"] if window is None else ["static", "motion"]
    fitted = {kind: _candidate(setup, kind) for kind in kinds}
    errors_mm = {kind: DistanceStats.of(c.sol.errors).mean for kind, c in fitted.items()}
    chosen, reason = choose_calibration(mode, errors_mm)
    choice, choice_notes = choice_report(
        mode, chosen, reason, errors_mm, {k: c.subject.cal.scales for k, c in fitted.items()},
        list(skel.segments), _measured_segments(skel, fitted[chosen].ik_names, setup.markers),
        None if check is None else check.as_dict(),
    )  # fmt: skip
    best = fitted[chosen]
    sol, subject = best.sol, best.subject
    t_end = time.perf_counter()
    report = _report(sol.q, sol.errors, best.observed, skel.ranges, best.iterations, t_end - t0)
    in_trial = {normalise_name(n) for n in trial.names}
    unused = sorted(in_trial - set(setup.markers.names))
    extra = _report_extra(
        defn.name, subject, sum(c.calibration_seconds for c in fitted.values()),
        sum(c.ik_seconds for c in fitted.values()), sol.errors, best.ik_names, unused,
    )  # fmt: skip
    extra["notes"] = [*extra["notes"], *choice_notes]
    pinned = at_limits(skel, sol.q, setup.plan, best.unobservable)
    extra.update(calibration_choice=choice, unobservable=best.unobservable, at_limit=pinned)
    if pinned:
        extra["notes"].append(
            f"at a joint limit in most frames: {', '.join(pinned)}; the markers pull them beyond their range "
            "(check that the markers are named and placed as the set defines them)"
        )
    return MarkerFit(
        sol.q, sol.root, trial.times.copy(), subject.cal.scales, subject.markers, sol.errors,
        subject.standing, defn.name, list(skel.dof_names),
        replace(report, extra=extra),
    )  # fmt: skip


def _measured_segments(skel: Skeleton, names: list[str], markers: VirtualMarkers) -> np.ndarray:
    """(n_seg,) bool: the scale segments whose bodies carry at least two of the markers ``names``."""
    count = np.zeros(len(skel.segments), int)
    for b in markers.subset(names).body_indices(skel):
        count[skel.spec.body_segment_index[b]] += 1
    return count >= 2


@dataclass(frozen=True)
class _Setup:
    """What every calibration of one :func:`fit_markers` call shares: the skeleton, the scale model, the
    set's (weighted) virtual markers and name, the IK plan and the static trial's plan, the motion, the
    static window (or None), the held coordinates and the calibration frame count and iterations."""

    skel: Skeleton
    scale_model: ScaleModel
    markers: VirtualMarkers
    set_name: str
    plan: DofPlan
    standing_plan: DofPlan
    trial: MarkerTrial
    window: MarkerTrial | None
    static_pose: Mapping[str, float] | None
    calibration_frames: int
    max_iterations: int
    calibration_held: tuple[str, ...] = ()

    def placing(self, markers: VirtualMarkers, place: np.ndarray) -> DofPlan:
        """The IK plan for a calibration that places the markers ``place`` (M,) bool of ``markers``: the
        set's ``calibration_held`` coordinates that move a placed marker are held near neutral (their zero
        and the placed markers' locations trade off one to one, see :mod:`.marker_sets`)."""
        on = np.zeros(len(self.skel.body_names), bool)
        on[np.asarray(markers.body_indices(self.skel))[place]] = True
        held = [n for n in self.calibration_held if (moved_bodies(self.skel, [n]) & on).any()]
        return holding_neutral(self.skel, self.plan, held) if held else self.plan


@dataclass(frozen=True)
class _Candidate:
    """One calibration and the IK of the whole motion with it: the subject, the IK marker names and their
    observed positions (T, M, 3), the solution, the unobservable coordinates (name -> reason), LM steps
    and seconds."""

    subject: _Subject
    ik_names: list[str]
    observed: np.ndarray
    sol: IKSolution
    unobservable: dict[str, str]
    iterations: int
    calibration_seconds: float
    ik_seconds: float


def _candidate(setup: _Setup, kind: str) -> _Candidate:
    """Calibrate the subject the ``kind`` way (``"static"`` / ``"motion"``), find the coordinates its
    markers cannot determine, hold them near neutral and solve the IK of every frame."""
    t0 = time.perf_counter()
    skel, trial = setup.skel, setup.trial
    in_trial = {normalise_name(n) for n in trial.names}
    vm = setup.markers.subset(
        _used_names(setup.markers, in_trial, setup.window if kind == "static" else None)
    )
    if kind == "static":
        assert setup.window is not None
        subject = _subject_from_static(setup, vm, in_trial)
    else:
        subject = _subject_from_motion(setup, vm)
    t_cal = time.perf_counter()
    ik_names = [n for n in subject.markers.names if n in in_trial]
    ik_markers = subject.markers.subset(ik_names)
    cal = subject.cal
    hidden = unobservable(skel, ik_markers, cal.scales, cal.q, cal.root, setup.plan)
    plan = holding_neutral(skel, setup.plan, list(hidden))
    observed = observed_positions(trial, ik_names)
    sol = solve_ik(
        skel, ik_markers, cal.scales, observed, trial.times, plan, max_iterations=setup.max_iterations
    )
    return _Candidate(
        subject, ik_names, observed, sol, hidden, cal.iterations + sol.iterations, t_cal - t0,
        time.perf_counter() - t_cal,
    )  # fmt: skip


def _weighted(vm: VirtualMarkers, weights: Mapping[str, float] | None, set_name: str) -> VirtualMarkers:
    """The markers ``vm`` with their IK weights overridden by ``weights`` (marker name -> weight).

    Raises:
        MarkerSetError: a name in ``weights`` that is not a marker of the set.
    """
    if not weights:
        return vm
    unknown = sorted(set(weights) - set(vm.names))
    if unknown:
        raise MarkerSetError(f"weights name markers not in the {set_name} set: {', '.join(unknown)}")
    w = vm.weights.copy()
    for n, v in weights.items():
        w[vm.names.index(n)] = float(v)
    return replace(vm, weights=w)


def _used_names(vm: VirtualMarkers, in_trial: set[str], static: MarkerTrial | None) -> list[str]:
    """Names of the weighted markers of ``vm`` that the trial (names ``in_trial``) or, when calibrating
    from it, the static trial ``static`` shows (every marker a static trial shows is placed)."""
    in_static: set[str] = set()
    if static is not None:
        in_static = {normalise_name(n) for n in static.names}
    return [n for n, wt in zip(vm.names, vm.weights) if wt > 0 and (n in in_trial or n in in_static)]


@dataclass(frozen=True)
class _Subject:
    """A calibrated subject: the calibration, its markers, the static standing pose (n_dof,) or None, how
    it was calibrated (for the report) and notes for the report."""

    cal: Calibration
    markers: VirtualMarkers
    standing: np.ndarray | None
    described: str
    notes: list[str]


def _subject_from_static(setup: _Setup, vm: VirtualMarkers, in_trial: set[str]) -> _Subject:
    """The subject calibrated from the static trial (see :func:`_calibrate_static`), then its technical
    markers and the markers above the pelvis refined on frames of the motion (:func:`_refine_on_motion`)."""
    assert setup.window is not None
    used = list(vm.names)
    static_frames = observed_positions(setup.window, used)
    cal, markers, hidden = _calibrate_static(
        setup.skel, setup.scale_model, vm, static_frames, setup.standing_plan, setup.set_name
    )
    standing = cal.q[0]
    notes: list[str] = []
    if hidden:
        notes.append(
            f"held near neutral in the static pose (its markers cannot determine them): {', '.join(hidden)}"
        )
    missing = [
        n for n in used if n in in_trial and not np.isfinite(_frame_mean(static_frames)[used.index(n)]).all()
    ]
    if missing:
        notes.append(f"not in the static trial, left at their default locations: {', '.join(missing)}")
    pinned = at_limits(setup.skel, standing[None], setup.standing_plan, hidden)
    if pinned:
        # The markers placed in this pose carry what the limit kept from the pose: the motion's readings of
        # these coordinates start from the limit, not from where the subject stood.
        notes.append(
            f"at a joint limit in the static pose: {', '.join(pinned)}; its anatomical markers pull them "
            "beyond their range (a subject standing beyond it, or markers placed otherwise than the set "
            "defines them)"
        )
    refined, described = _refine_on_motion(setup, cal, markers, vm)
    return _Subject(refined, refined.markers, standing, described, notes)


def _refine_on_motion(
    setup: _Setup, static: Calibration, markers: VirtualMarkers, defaults: VirtualMarkers
) -> tuple[Calibration, str]:
    """A static calibration refined on frames of the motion, as a functional calibration: the scales
    stay within :data:`REFINE_SCALE_SIGMA` of the static trial's, the anatomical markers of the pelvis and
    legs stay where the static trial placed them (they set the coordinates' zeros), and the technical
    markers of the pelvis and legs move from their static places, with the prior of
    :func:`~.subject.calibrate`. The markers above the pelvis start from and are pulled towards their
    ``defaults`` (the template's places) instead: the skin over the shoulders and arms moves with the arms'
    pose, and a static trial's arm pose (often abducted, its forearm rotation barely seen) places them
    worse than the motion does. Returns the calibration (q, root: the frames') and a description."""
    skel, trial = setup.skel, setup.trial
    names = [n for n in markers.names if n in {normalise_name(t) for t in trial.names}]
    moving = markers.subset(names)
    obs = observed_positions(trial, names)
    frames = _calibration_frames(obs, setup.calibration_frames)
    lower = np.array([b.startswith(LOWER_BODIES) for b in moving.bodies])
    arm = np.array([b.startswith(ARM_BODIES) for b in moving.bodies])
    place = ~moving.anatomical | ~(lower | arm)
    start_local = np.where(lower[:, None], moving.local, defaults.subset(names).local)
    moving = replace(moving, local=start_local)
    first = solve_ik(skel, moving, static.scales, obs[frames], trial.times[frames], setup.plan)
    centre, sigma = _refine_scale_prior(skel, setup.scale_model, static.scales)
    cal = calibrate(
        skel, setup.scale_model.centred(centre), moving, obs[frames], trial.times[frames],
        setup.placing(moving, place), place, start=first.q, scale_sigma=sigma,
    )  # fmt: skip
    # The markers only the static trial shows keep their static places.
    local = markers.local.copy()
    local[[markers.names.index(n) for n in names]] = cal.markers.local
    cal = replace(cal, markers=replace(markers, local=local))
    described = f"static, technical and upper-body markers refined on {len(frames)} frames of the motion"
    return cal, described


def _refine_scale_prior(
    skel: Skeleton, scale_model: ScaleModel, static_scales: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Centre (n_seg, 3) and sigma (n_free, 3) of the scales when a static calibration is refined on the
    motion: the pelvis and legs keep the static trial's scales (within :data:`REFINE_SCALE_SIGMA`); the
    segments above start from the population mean with the motion calibration's prior (a static trial's
    arm pose scales the arms poorly, see :func:`_refine_on_motion`)."""
    lower = np.array([s.startswith(LOWER_BODIES) for s in skel.segments])
    centre = np.where(lower[:, None], static_scales, scale_model.mean.numpy())
    tie = scale_model.tie.numpy()
    sigma = np.full((scale_model.n_free, 3), SCALE_SIGMA)
    sigma[tie[lower]] = REFINE_SCALE_SIGMA
    return centre, sigma


def _subject_from_motion(setup: _Setup, vm: VirtualMarkers) -> _Subject:
    """The subject calibrated from frames of the motion; with a static trial and ``static_pose``, the
    markers on the bodies the held coordinates move are then placed where the static trial saw them (see
    :func:`_place_from_static`)."""
    skel, trial = setup.skel, setup.trial
    obs = observed_positions(trial, list(vm.names))
    frames = _calibration_frames(obs, setup.calibration_frames)
    first = solve_ik(skel, vm, setup.scale_model.mean.numpy(), obs[frames], trial.times[frames], setup.plan)
    cal = calibrate(
        skel,
        setup.scale_model,
        vm,
        obs[frames],
        trial.times[frames],
        setup.placing(vm, ~vm.anatomical),
        ~vm.anatomical,
        start=first.q,
    )
    markers, described = cal.markers, f"motion ({len(cal.q)} frames)"
    standing: np.ndarray | None = None
    if setup.window is not None and setup.static_pose:
        static_frames = observed_positions(setup.window, list(markers.names))
        markers, standing, bodies = _place_from_static(
            skel, markers, cal.scales, static_frames, setup.standing_plan, setup.static_pose
        )
        described += (
            f"; the markers on {', '.join(bodies)} placed from the static trial with "
            f"{', '.join(setup.static_pose)} held"
        )
    return _Subject(cal, markers, standing, described, [])


def _report_extra(
    set_name: str,
    subject: _Subject,
    calibration_seconds: float,
    ik_seconds: float,
    errors: np.ndarray,
    names: list[str],
    unused: list[str],
) -> dict[str, Any]:
    """The marker fit's numbers for :attr:`FitReport.extra` (errors: (T, M) m of the markers ``names``)."""
    return {
        "marker_set": set_name,
        "calibration": subject.described,
        "calibration_seconds": calibration_seconds,
        "ik_seconds": ik_seconds,
        "calibration_error_mm": DistanceStats.of(subject.cal.errors).mean,
        "marker_mean_error_mm": _mean_errors_mm(errors, names),
        "unused_markers": unused,
        "notes": subject.notes,
    }


def _mean_errors_mm(errors: np.ndarray, names: list[str]) -> dict[str, float]:
    """Mean error (mm) of each marker ``names[i]`` (errors (T, M) m, NaN where missing) that has any."""
    return {
        n: float(np.nanmean(errors[:, i]) * 1000)
        for i, n in enumerate(names)
        if np.isfinite(errors[:, i]).any()
    }


def _calibrate_static(
    skel: Skeleton,
    scale_model: ScaleModel,
    markers: VirtualMarkers,
    frames: np.ndarray,
    plan: DofPlan,
    set_name: str,
) -> tuple[Calibration, VirtualMarkers, dict[str, str]]:
    """Scales and standing pose from the anatomical markers of a static trial (frames (K, M, 3), averaged),
    then every marker it shows placed where it was seen (OpenSim's ScaleTool + MarkerPlacer). The
    coordinates the anatomical markers cannot determine in that pose (:mod:`.observability`) are held near
    neutral; they are returned (name -> reason) with the calibration and the placed markers."""
    mean = _frame_mean(frames)
    seen = np.isfinite(mean).all(-1)
    anat = markers.anatomical & seen
    if anat.sum() < MIN_VISIBLE:
        raise MarkerSetError(
            f"the static trial shows {int(anat.sum())} anatomical markers of the {set_name} set; at least "
            f"{MIN_VISIBLE} are needed to scale the subject (or calibrate from the motion: static=None)"
        )
    fit_markers_ = replace(markers, weights=np.where(anat, markers.weights, 0.0))
    nothing = np.zeros(len(seen), bool)
    cal = calibrate(skel, scale_model, fit_markers_, mean[None], np.zeros(1), plan, nothing)
    # A standing pose leaves some coordinates undetermined (forearm rotation with straight elbows): solve
    # it again with those held at neutral, as a lab's scale setup holds them.
    hidden = unobservable(skel, fit_markers_, cal.scales, cal.q, cal.root, plan)
    if hidden:
        start = cal.q.copy()
        start[:, [skel.dof_index(n) for n in hidden]] = 0.0
        held = holding_neutral(skel, plan, list(hidden))
        cal = calibrate(skel, scale_model, fit_markers_, mean[None], np.zeros(1), held, nothing, start=start)
    placed = place_markers(skel, markers, mean, cal.q[0], cal.root[0], cal.scales, seen)
    return cal, placed, hidden


def _calibration_mode(
    calibration: str, static: MarkerTrial | None, static_pose: Mapping[str, float] | None
) -> str:
    """ "auto", "static" or "motion": how :func:`fit_markers` calibrates (see there; "auto" only with a
    static trial); ValueError on a combination that would leave an argument unused."""
    if calibration not in ("auto", "static", "motion"):
        raise ValueError(f"calibration must be 'auto', 'static' or 'motion', not {calibration!r}")
    if static is None:
        if calibration == "static":
            raise ValueError("calibration='static' needs the static trial: pass it, or use 'motion'")
        if static_pose:
            raise ValueError("static_pose holds coordinates in a static trial's pose: pass the static trial")
        return "motion"
    if calibration == "motion" and not static_pose:
        raise ValueError(
            "with calibration='motion' a static trial only places the markers of the coordinates static_pose "
            "holds: pass static_pose, or calibrate from the static trial (calibration='static')"
        )
    return calibration


def _frame_mean(frames: np.ndarray) -> np.ndarray:
    """(M, 3) the mean of frames (K, M, 3) over K, NaN for a marker no frame shows."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # markers absent from the static trial
        return np.nanmean(frames, axis=0)


def _place_from_static(
    skel: Skeleton,
    markers: VirtualMarkers,
    scales: np.ndarray,
    frames: np.ndarray,
    holding: DofPlan,
    held: Iterable[str],
) -> tuple[VirtualMarkers, np.ndarray, list[str]]:
    """The markers on the bodies the coordinates ``held`` move, placed where a static trial (frames
    (K, M, 3) of ``markers``, averaged) saw them in its pose: solved from all the markers where they are,
    by the plan ``holding`` that holds those coordinates (scales (n_seg, 3): the subject's), as OpenSim's
    MarkerPlacer solves it before it moves them. Returns the markers, that pose (n_dof,) and the names of
    the bodies whose markers were placed."""
    held = list(held)
    mean = _frame_mean(frames)
    on = moved_bodies(skel, held)[markers.body_indices(skel)] & np.isfinite(mean).all(-1)
    if not on.any():
        raise MarkerSetError(
            f"the static trial shows no marker on the bodies that {', '.join(held)} move: nothing to place"
        )
    pose = solve_ik(skel, markers, scales, mean[None], np.zeros(1), holding, stride=1)
    placed = place_markers(skel, markers, mean, pose.q[0], pose.root[0], scales, on)
    return placed, pose.q[0], sorted({markers.bodies[i] for i in np.flatnonzero(on)})


def _report(
    q: np.ndarray,
    errors: np.ndarray,
    observed: np.ndarray,
    ranges: np.ndarray,
    iterations: int,
    seconds: float,
) -> FitReport:
    """The fit's error report. q: (T, n_dof); errors: (T, M) m; observed: (T, M, 3); ranges: (n_dof, 2)."""
    reasons: list[str] = []
    visible = np.isfinite(observed).all(-1).sum(-1)
    if (visible < MIN_VISIBLE).any():
        reasons.append(f"{int((visible < MIN_VISIBLE).sum())} frames show fewer than {MIN_VISIBLE} markers")
    mean_error = float(np.nanmean(errors)) if np.isfinite(errors).any() else float("nan")
    if not mean_error <= MAX_MEAN_ERROR:
        reasons.append(
            f"mean marker error {mean_error * 1000:.1f} mm exceeds {MAX_MEAN_ERROR * 1000:.0f} mm: check "
            "marker names and labelling, the static trial, or the lab-to-world rotation"
        )
    return FitReport.judged(DistanceStats.of(errors), q, ranges, iterations, seconds, reasons)

"""Mocap subject calibration: static against motion calibration compared and reported, static trials from
another protocol or subject refused, coordinates the markers cannot determine reported and held, and
coordinates kept at a joint limit reported."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bodyfit.io.mocap import MarkerTrial, read_trc
from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.mocap.calibration import DofPlan
from bodyfit.models.fitting.mocap.choice import STATIC_TOLERANCE, choose_calibration
from bodyfit.models.fitting.mocap.fitter import fit_markers
from bodyfit.models.fitting.mocap.marker_sets import GAIT2392, MarkerSetError
from bodyfit.models.fitting.mocap.observability import at_limits
from bodyfit.models.skeleton.opensim_export import read_mot

GAIT = Path(__file__).resolve().parents[1] / "data" / "opensim_gait"


@pytest.fixture(scope="module")
def body() -> BodyModel:
    return BodyModel.load()


@pytest.fixture(scope="module")
def walk() -> MarkerTrial:
    """0.5 s of the gait2392 walk (31 frames)."""
    return read_trc(GAIT / "gait2392_subject01_walk1.trc").between(0.6, 1.1)


@pytest.fixture(scope="module")
def static() -> MarkerTrial:
    return read_trc(GAIT / "gait2392_subject01_static.trc")


def test_auto_compares_both_calibrations_and_reports_the_choice(body, walk, static) -> None:
    fit = fit_markers(walk, static, model=body, calibration_frames=8)
    choice = fit.report.extra["calibration_choice"]
    errors = choice["marker_error_mm"]
    assert set(errors) == {"static", "motion"} and all(5.0 < e < 20.0 for e in errors.values())
    # The kept calibration is the one whose IK is returned.
    assert fit.report.distances.mean == pytest.approx(errors[choice["chosen"]])
    assert choice["requested"] == "auto" and choice["chosen"] == "static"
    assert errors["static"] <= STATIC_TOLERANCE * errors["motion"]
    assert "static kept" in choice["reason"] and f"{errors['motion']:.1f} mm" in choice["reason"]
    assert choice["static_check"]["pair_distance_difference"] < 0.02
    # An explicit choice is kept and carries the same comparison.
    asked = fit_markers(walk, static, model=body, calibration="motion", calibration_frames=8,
                        static_pose={"ankle_angle_r": 0.0, "ankle_angle_l": 0.0})  # fmt: skip
    assert asked.report.extra["calibration_choice"]["chosen"] == "motion"
    assert set(asked.report.extra["calibration_choice"]["marker_error_mm"]) == {"static", "motion"}
    assert "asked for" in asked.report.extra["calibration_choice"]["reason"]


def test_a_static_pose_at_a_joint_limit_is_reported(body, walk, static) -> None:
    """The gait2392 subject's anatomical knee markers sit 1-2 cm behind where our knee at full extension
    puts them: the static pose holds both knees at their limit, and the report says so."""
    fit = fit_markers(walk, static, model=body, calibration="static", calibration_frames=8)
    assert fit.static_coordinates is not None
    for side in ("r", "l"):
        assert fit.static_coordinates[body.skeleton.dof_index(f"knee_angle_{side}")] == pytest.approx(0.0)
    (note,) = [n for n in fit.report.extra["notes"] if "static pose:" in n and "joint limit" in n]
    assert "knee_angle_r" in note and "knee_angle_l" in note and "hip_flexion" not in note


def test_a_disagreeing_static_trial_falls_back_with_the_reason() -> None:
    chosen, reason = choose_calibration("auto", {"static": 23.5, "motion": 9.6})
    assert chosen == "motion" and "disagrees" in reason and "23.5" in reason and "9.6" in reason
    chosen, reason = choose_calibration("static", {"static": 23.5, "motion": 9.6})
    assert chosen == "static" and "calibration='auto' or 'motion'" in reason
    chosen, reason = choose_calibration("auto", {"static": 10.0, "motion": 9.0})
    assert chosen == "static" and "within" in reason
    assert choose_calibration("auto", {"motion": 9.0})[0] == "motion"


def test_a_static_trial_of_another_protocol_is_refused(body, walk, static) -> None:
    renamed = tuple(n if i < 5 else f"{n}_lab2" for i, n in enumerate(static.names))
    other = MarkerTrial(renamed, static.positions, static.rate, static.times)
    with pytest.raises(MarkerSetError, match=r"shows 5 of the motion's 41 gait2392 markers.*protocol"):
        fit_markers(walk, other, model=body)


def test_a_static_trial_of_another_subject_is_refused(body, walk) -> None:
    hamner_static = read_trc(GAIT / "hamner_subject02_static.trc")
    with pytest.raises(MarkerSetError, match="another subject"):
        fit_markers(walk, hamner_static, model=body)


def test_unobservable_coordinates_are_reported_and_held_near_neutral(body, walk) -> None:
    """Without the right wrist's markers nothing sees the right elbow and forearm; without head markers,
    nothing sees the neck: they are reported with the reason and held at 0, not solved to a limit."""
    off = {"R.Wrist.Med": 0.0, "R.Wrist.Lat": 0.0, "Top.Head": 0.0, "R.Temple": 0.0, "L.Temple": 0.0}
    fit = fit_markers(walk, model=body, weights=off, calibration_frames=8)
    hidden = fit.report.extra["unobservable"]
    skel = body.skeleton
    for name in ("elbow_flex_r", "pro_sup_r", "neck_extension", "neck_rotation"):
        assert name in hidden and "no marker on" in hidden[name], hidden
        assert np.abs(np.degrees(fit.coordinates[:, skel.dof_index(name)])).max() < 1.0
    # The left forearm keeps its markers and stays observable.
    assert "pro_sup_l" not in hidden and "elbow_flex_l" not in hidden
    assert fit.report.limit_violations == 0


def test_coordinates_kept_at_a_limit_are_reported(body) -> None:
    skel = body.skeleton
    plan = DofPlan.build(skel, GAIT2392)
    q = np.zeros((10, skel.n_dof))
    elbow, pro_sup = skel.dof_index("elbow_flex_r"), skel.dof_index("pro_sup_l")
    q[:, elbow] = np.radians(40.0)
    q[:6, elbow] = skel.ranges[elbow, 1]  # 6 of 10 frames at full flexion
    q[:, pro_sup] = skel.ranges[pro_sup, 1]
    q[:, skel.dof_index("hip_flexion_r")] = np.radians(10.0)
    pinned = at_limits(skel, q, plan, {"pro_sup_l": "held"})
    assert pinned["elbow_flex_r"] == pytest.approx(0.6)
    assert "pro_sup_l" not in pinned and "hip_flexion_r" not in pinned


def test_the_forearms_zero_is_held_while_its_markers_are_placed(body) -> None:
    """The gait2392 protocol's wrist markers are placed from the motion; a constant forearm rotation and a
    turn of their places about the forearm are the same motion of the markers, so calibration holds pro_sup
    near the model's zero. On the Hamner run pro_sup then follows OpenSim's reference (6-12 degrees there)
    instead of sitting at its 90-degree limit, and the fit reports no coordinate pinned at a limit."""
    run = read_trc(GAIT / "hamner_subject02_running.trc").between(0.0, 1.0)
    fit = fit_markers(run, model=body, calibration_frames=8)
    skel = body.skeleton
    cols, data, _ = read_mot(GAIT / "hamner_subject02_running_ik.mot")
    sel = data[:, 0] <= fit.times[-1] + 1e-9
    for side in ("r", "l"):
        name = f"pro_sup_{side}"
        ours = np.degrees(np.interp(data[sel, 0], fit.times, fit.coordinates[:, skel.dof_index(name)]))
        assert np.sqrt(np.mean((ours - data[sel, cols.index(name)]) ** 2)) < 15.0, name
        assert ours.max() < 60.0 and name not in fit.report.extra["unobservable"]
    assert not any(n.startswith("pro_sup") for n in fit.report.extra["at_limit"])

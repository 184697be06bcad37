"""Mocap markers -> coordinates: marker sets, Jacobians, solver, recovery, the real OpenSim trials.
(The file readers are tested in test_mocap_io.py.)"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import torch

from bodyfit.io.mocap import (
    MarkerTrial,
    read_trc,
)
from bodyfit.models.body.model import BodyModel
from bodyfit.models.errors import UnknownCoordinateError
from bodyfit.models.fitting.mocap.calibration import DofPlan, moved_bodies, virtual_markers
from bodyfit.models.fitting.mocap.fitter import fit_markers
from bodyfit.models.fitting.mocap.marker_ik import (
    MarkerChain,
    levenberg_marquardt,
    marker_jacobian,
    marker_positions,
)
from bodyfit.models.fitting.mocap.marker_sets import (
    GAIT2392,
    RAJAGOPAL,
    RAJAGOPAL_MARKERS,
    MarkerSetError,
    choose_marker_set,
)
from bodyfit.models.fitting.mocap.marker_solve import solve_ik
from bodyfit.models.skeleton import Skeleton
from bodyfit.models.skeleton.model import twin_name
from bodyfit.models.skeleton.opensim_export import read_mot

DATA = Path(__file__).resolve().parents[1] / "data"
GAIT = DATA / "opensim_gait"
FLEXION = [f"{j}_{s}" for s in ("r", "l") for j in ("hip_flexion", "knee_angle", "ankle_angle")]


@pytest.fixture(scope="module")
def body() -> BodyModel:
    return BodyModel.load()


def rmse_against_reference(
    fit_times: np.ndarray, q: np.ndarray, skel: Skeleton, mot: Path
) -> dict[str, float]:
    """Degrees RMSE per coordinate over the common time range (knee sign: OpenSim's gait models flex
    negative, Rajagopal's positive)."""
    cols, data, _ = read_mot(mot)
    sel = (data[:, 0] >= fit_times[0] - 1e-9) & (data[:, 0] <= fit_times[-1] + 1e-9)
    out = {}
    for name in FLEXION:
        ours = np.degrees(np.interp(data[sel, 0], fit_times, q[:, skel.dof_index(name)]))
        ref = data[sel, cols.index(name)] * (-1.0 if name.startswith("knee") else 1.0)
        out[name] = float(np.sqrt(np.mean((ours - ref) ** 2)))
    return out


# -- marker sets -----------------------------------------------------------------------------------------


def test_marker_set_choice_and_errors() -> None:
    walk = read_trc(GAIT / "gait2392_subject01_walk1.trc")
    assert choose_marker_set(walk.names).name == "gait2392"
    assert (
        choose_marker_set(["Subject:RASI", "LASI", "RPSI", "LPSI", "RTH1", "RCAL", "RTOE"]).name
        == "rajagopal"
    )
    with pytest.raises(MarkerSetError, match="unknown marker set 'cast'"):
        choose_marker_set(walk.names, "cast")
    with pytest.raises(MarkerSetError, match="shares 2 marker names"):
        choose_marker_set(["R.ASIS", "L.ASIS", "Foo"])


def test_rajagopal_marker_table_matches_the_osim() -> None:
    pytest.importorskip("nimblephysics", reason="Rajagopal2015.osim ships inside nimblephysics")
    from bodyfit.models.skeleton.rajagopal import rajagopal_osim_path

    root = ET.parse(rajagopal_osim_path()).getroot()
    found = {
        m.get("name"): (
            str(m.findtext("body")).strip(),
            tuple(float(v) for v in str(m.findtext("location")).split()),
        )
        for m in root.iter("Marker")
    }
    assert found == RAJAGOPAL_MARKERS


def test_virtual_markers_sit_on_their_bodies(body: BodyModel) -> None:
    for defn in (GAIT2392, RAJAGOPAL):
        vm = virtual_markers(defn, body)
        assert vm.local.shape == (len(defn.markers), 3) and np.isfinite(vm.local).all()
        assert np.abs(vm.local).max() < 0.75  # every marker within reach of its body's origin
    vm = virtual_markers(GAIT2392, body)
    i = vm.names.index("R.Knee.Lat")
    np.testing.assert_allclose(vm.local[i], [0.0, -0.404, 0.05])  # Rajagopal's RLFC, verbatim
    r, le = vm.local[vm.names.index("R.Toe.Tip")], vm.local[vm.names.index("L.Toe.Tip")]
    np.testing.assert_allclose(r * [1, 1, -1], le, atol=2e-3)  # left-right mirror images


def test_acromion_markers_keep_the_shoulders_where_they_are(gait_fit, running_fit, body: BodyModel) -> None:
    """The gait2392 Acromium sits lateral of the shoulder joint centre, over the humeral head, so the
    subject's acromion markers scale the thorax to a plausible width (from Rajagopal's RACR, 4 cm medial of
    that centre, both trials widened it by 50-60%)."""
    skel = body.skeleton
    vm = virtual_markers(GAIT2392, body)
    frames = skel.forward(np.zeros((1, skel.n_dof))).frames[0].double().numpy()
    for side, sign in (("r", 1.0), ("l", -1.0)):
        i = vm.names.index(f"{side.upper()}.Acromium")
        scapula = frames[skel.body_names.index(vm.bodies[i])]
        marker = scapula[:3, :3] @ vm.local[i] + scapula[:3, 3]
        shoulder = frames[skel.body_names.index(f"humerus_{side}"), :3, 3]
        torso = frames[skel.body_names.index("torso"), :3, :3]
        assert 0.0 < sign * (torso.T @ (marker - shoulder))[2] < 0.06
    thorax = skel.spec.body_segment_index[skel.body_names.index("thorax")]
    for fit in (gait_fit, running_fit):
        assert 0.85 < fit.scales[thorax, 2] < 1.2, fit.scales[thorax]


# -- Jacobians and the solver ----------------------------------------------------------------------------


def test_marker_jacobians_match_autograd(skeleton: Skeleton) -> None:
    fk = skeleton.kinematics(torch.float64)
    rng = np.random.default_rng(3)
    chain = MarkerChain.build(fk, list(range(len(skeleton.body_names))))
    local = torch.as_tensor(rng.normal(0, 0.1, (len(skeleton.body_names), 3)))
    q = torch.as_tensor(rng.uniform(skeleton.ranges[:, 0], skeleton.ranges[:, 1], (2, skeleton.n_dof)))
    root = torch.as_tensor(rng.normal(size=(2, 3)))
    scales = torch.as_tensor(rng.uniform(0.8, 1.2, (2, len(skeleton.segments), 3)))
    _, jq, js = marker_jacobian(fk, chain, local, q, root, scales, with_scales=True)
    assert js is not None

    def by_q(qr: torch.Tensor) -> torch.Tensor:
        return marker_positions(
            fk, chain, local, qr[:, : skeleton.n_dof], qr[:, skeleton.n_dof :], scales
        ).sum(0)

    ref_q = torch.autograd.functional.jacobian(by_q, torch.cat([q, root], 1))
    ref_s = torch.autograd.functional.jacobian(
        lambda s: marker_positions(fk, chain, local, q, root, s).sum(0), scales
    )
    for b in range(2):
        torch.testing.assert_close(jq[b], ref_q[:, :, b], atol=1e-12, rtol=0)
        torch.testing.assert_close(js[b], ref_s[:, :, b], atol=1e-12, rtol=0)


def test_box_constrained_lm_leaves_a_bound_when_pulled_inside() -> None:
    target = torch.tensor([[0.5, 3.0], [-2.0, 0.2]], dtype=torch.float64)

    def residual(x: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        J = torch.eye(2, dtype=x.dtype).expand(len(rows), 2, 2)
        return x - target[rows], J.clone()

    lo, hi = torch.tensor([-1.0, -1.0], dtype=torch.float64), torch.tensor([1.0, 1.0], dtype=torch.float64)
    start = torch.tensor([[-1.0, 1.0], [1.0, -1.0]], dtype=torch.float64)  # both on bounds
    res = levenberg_marquardt(residual, start, lo, hi)
    torch.testing.assert_close(
        res.x, torch.tensor([[0.5, 1.0], [-1.0, 0.2]], dtype=torch.float64), atol=1e-6, rtol=0
    )


def _synthetic(body: BodyModel, q: np.ndarray, root: np.ndarray, scales: np.ndarray, noise: float, seed: int):
    """Gait2392 markers generated by our skeleton: (trial, markers)."""
    skel = body.skeleton
    vm = virtual_markers(GAIT2392, body)
    fk = skel.kinematics(torch.float64)
    chain = MarkerChain.build(fk, vm.body_indices(skel))
    pos = marker_positions(
        fk, chain, torch.as_tensor(vm.local), torch.as_tensor(q), torch.as_tensor(root),
        torch.as_tensor(scales).expand(len(q), -1, -1),
    ).numpy()  # fmt: skip
    pos = pos + np.random.default_rng(seed).normal(0, noise, pos.shape)
    return MarkerTrial(vm.names, pos, 100.0, np.arange(len(q)) / 100.0), vm


def _gait_like(skel: Skeleton, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, n_dof) walking-like poses (lower body, trunk, elbows) and (n, 3) roots."""
    rng = np.random.default_rng(seed)
    spread = {
        "pelvis_tilt": 10, "pelvis_list": 8, "pelvis_rotation": 20, "lumbar_extension": 10,
        "lumbar_bending": 8, "lumbar_rotation": 10, "arm_flex_r": 20, "arm_flex_l": 20,
        "elbow_flex_r": 30, "elbow_flex_l": 30,
    }  # fmt: skip
    for s in ("r", "l"):
        spread.update({f"hip_flexion_{s}": 25, f"hip_adduction_{s}": 8, f"hip_rotation_{s}": 10})
        spread.update({f"knee_angle_{s}": 35, f"ankle_angle_{s}": 15})
    q = np.zeros((n, skel.n_dof))
    for name, deg in spread.items():
        q[:, skel.dof_index(name)] = np.radians(rng.uniform(-deg, deg, n))
    for s in ("r", "l"):
        k = skel.dof_index(f"knee_angle_{s}")
        q[:, k] = np.abs(q[:, k]) + 0.05
        q[:, skel.dof_index(f"elbow_flex_{s}")] = np.abs(q[:, skel.dof_index(f"elbow_flex_{s}")]) + 0.2
    root = np.c_[rng.uniform(-1, 1, n), rng.uniform(0.9, 1.0, n), rng.uniform(-0.2, 0.2, n)]
    return q, root


def test_ik_recovers_known_coordinates(body: BodyModel) -> None:
    skel = body.skeleton
    q, root = _gait_like(skel, 40, seed=1)
    scales = body.data["scale_mean"].astype(np.float64)
    trial, vm = _synthetic(body, q, root, scales, noise=0.001, seed=2)
    sol = solve_ik(skel, vm, scales, trial.positions, trial.times, DofPlan.build(skel, GAIT2392), stride=1)
    err = np.degrees(np.abs(sol.q - q))
    watched = [skel.dof_index(n) for n in (*FLEXION, "pelvis_tilt", "pelvis_list", "pelvis_rotation")]
    assert err[:, watched].max() < 1.5, err[:, watched].max(0)
    assert np.sqrt(np.mean(err[:, watched] ** 2)) < 0.5
    np.testing.assert_allclose(sol.root, root, atol=0.005)
    assert np.nanmean(sol.errors) < 0.003


def test_fit_with_static_recovers_pose_and_limits_hold(body: BodyModel) -> None:
    skel = body.skeleton
    rng = np.random.default_rng(5)
    factor = {s: rng.uniform(0.95, 1.05) for s in skel.segments if not s.endswith("_l")}
    subject = [factor[twin_name(s) if s.endswith("_l") else s] for s in skel.segments]  # symmetric
    scales = body.data["scale_mean"].astype(np.float64) * np.array(subject)[:, None]
    static_q = np.zeros((10, skel.n_dof))
    static, _ = _synthetic(body, static_q, np.tile([0.0, 0.95, 0.0], (10, 1)), scales, 0.001, 6)
    q, root = _gait_like(skel, 30, seed=7)
    q[:5, skel.dof_index("knee_angle_r")] = -0.1  # hyperextension the skeleton cannot follow
    trial, _ = _synthetic(body, q, root, scales, 0.001, 8)
    fit = fit_markers(trial, static, "gait2392", model=body)
    assert fit.report.limit_violations == 0 and fit.report.confident, fit.report.reasons
    lo, hi = skel.ranges[:, 0], skel.ranges[:, 1]
    assert ((fit.coordinates >= lo) & (fit.coordinates <= hi)).all()
    np.testing.assert_array_equal(fit.coordinates[:5, skel.dof_index("knee_angle_r")], 0.0)
    err = np.degrees(np.abs(fit.coordinates - q))[5:]
    assert err[:, [skel.dof_index(n) for n in FLEXION]].max() < 2.0
    assert fit.report.distances.mean < 5.0  # mm
    for seg in ("femur_r", "tibia_l"):  # bone lengths (y) from the knee and ankle markers
        i = skel.segments.index(seg)
        assert abs(fit.scales[i, 1] / scales[i, 1] - 1) < 0.01


def test_fit_errors(body: BodyModel) -> None:
    walk = read_trc(GAIT / "gait2392_subject01_walk1.trc")
    with pytest.raises(MarkerSetError, match="unknown marker set"):
        fit_markers(walk, marker_set="plug-in-gait", model=body)  # type: ignore[arg-type]
    with pytest.raises(MarkerSetError, match="not in the gait2392 set"):
        fit_markers(walk, weights={"NOPE": 1.0}, model=body)
    few = walk.frames(slice(0, 3))
    few = MarkerTrial(few.names[:8], few.positions[:, :8], few.rate, few.times)
    static = MarkerTrial(few.names, few.positions, few.rate, few.times)
    with pytest.raises(MarkerSetError, match="anatomical markers"):
        fit_markers(few, static, model=body)


# -- the real OpenSim trials -----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def gait_fit(body: BodyModel):
    walk = read_trc(GAIT / "gait2392_subject01_walk1.trc")
    static = read_trc(GAIT / "gait2392_subject01_static.trc")
    return fit_markers(walk, static, model=body)


def test_gait2392_walk_matches_opensim_within_5_degrees(gait_fit, body: BodyModel) -> None:
    rmse = rmse_against_reference(
        gait_fit.times, gait_fit.coordinates, body.skeleton, GAIT / "gait2392_subject01_walk1_ik.mot"
    )
    assert max(rmse.values()) <= 5.0, rmse
    assert gait_fit.report.limit_violations == 0 and gait_fit.report.confident
    assert gait_fit.report.distances.mean < 20.0  # mm; OpenSim's own fit of this trial: 23 mm RMS
    assert gait_fit.marker_set == "gait2392" and gait_fit.static_coordinates is not None


# The Hamner pipeline's scale setup (Setup_Scale.xml) holds the ankles at 0.5 degrees in the static pose.
HAMNER_ANKLES = {"ankle_angle_r": np.radians(0.5), "ankle_angle_l": np.radians(0.5)}


@pytest.fixture(scope="module")
def running_fit(body: BodyModel):
    """The Hamner running copy calibrated from 16 frames of its motion."""
    return fit_markers(read_trc(GAIT / "hamner_subject02_running.trc"), model=body, calibration_frames=16)


def test_running_without_static_trial(running_fit, body: BodyModel) -> None:
    run = read_trc(GAIT / "hamner_subject02_running.trc")
    assert np.isnan(run.marker("L.Bicep")).all()  # written as 0 0 0 in the file
    fit = running_fit
    rmse = rmse_against_reference(
        fit.times, fit.coordinates, body.skeleton, GAIT / "hamner_subject02_running_ik.mot"
    )
    assert max(rmse[n] for n in FLEXION if not n.startswith("ankle")) <= 5.0, rmse
    # Ankle: Hamner2010's generic toe marker sits 2.8 cm higher on the foot than gait2392's and ours, a
    # constant plantarflexion offset of its reference (see the benchmark); the motion itself matches.
    cols, data, _ = read_mot(GAIT / "hamner_subject02_running_ik.mot")
    for s in ("r", "l"):
        ours = np.degrees(
            np.interp(data[:, 0], fit.times, fit.coordinates[:, body.skeleton.dof_index(f"ankle_angle_{s}")])
        )
        diff = ours - data[:, cols.index(f"ankle_angle_{s}")]
        assert diff.std() < 3.0 and 3.0 < diff.mean() < 12.0
    assert fit.report.limit_violations == 0 and "motion" in fit.report.extra["calibration"]


def test_running_with_the_ankles_zeroed_by_the_static_trial(running_fit, body: BodyModel) -> None:
    """Calibrated from the motion, then the feet's markers placed from the static trial in its pose with the
    ankles held where the lab's scale setup holds them: every flexion within 5 degrees of OpenSim's
    reference, the ankle's constant offset gone (without the static trial it reads 3-12 degrees more,
    above), and every other marker where the motion's calibration put it."""
    run = read_trc(GAIT / "hamner_subject02_running.trc")
    static = read_trc(GAIT / "hamner_subject02_static.trc")
    fit = fit_markers(
        run, static, model=body, calibration="motion", static_pose=HAMNER_ANKLES, calibration_frames=16
    )
    rmse = rmse_against_reference(
        fit.times, fit.coordinates, body.skeleton, GAIT / "hamner_subject02_running_ik.mot"
    )
    assert max(rmse.values()) <= 5.0 and max(rmse[f"ankle_angle_{s}"] for s in "rl") <= 3.0, rmse
    assert fit.static_coordinates is not None and fit.report.limit_violations == 0
    for name, value in HAMNER_ANKLES.items():
        assert fit.static_coordinates[body.skeleton.dof_index(name)] == pytest.approx(value)
    feet = np.array([b.startswith(("calcn", "toes")) for b in fit.markers.bodies])
    assert feet.sum() == 12 and fit.markers.names == running_fit.markers.names
    np.testing.assert_array_equal(fit.markers.local[~feet], running_fit.markers.local[~feet])
    assert np.linalg.norm(fit.markers.local[feet] - running_fit.markers.local[feet], axis=1).max() > 0.01
    assert "calcn_r" in fit.report.extra["calibration"]


def test_a_static_calibration_holds_the_static_pose_it_is_given(body: BodyModel) -> None:
    """With ``static_pose`` a static calibration solves the standing pose with those coordinates held (the
    gait2392 pipeline's scale setup holds the lumbar extension at 0): the pose has them exactly, and the
    thoracic spine above takes up the extension the lumbar joint no longer carries."""
    walk = read_trc(GAIT / "gait2392_subject01_walk1.trc").between(0.5, 1.0)
    static = read_trc(GAIT / "gait2392_subject01_static.trc")
    free = fit_markers(walk, static, model=body)
    held = fit_markers(walk, static, model=body, static_pose={"lumbar_extension": 0.0})
    lumbar = body.skeleton.dof_index("lumbar_extension")
    assert free.static_coordinates is not None and held.static_coordinates is not None
    assert abs(free.static_coordinates[lumbar]) > np.radians(1.0) and held.static_coordinates[lumbar] == 0.0
    thorax = body.skeleton.dof_index("thorax_extension")
    moved = held.static_coordinates[thorax] - free.static_coordinates[thorax]
    assert np.sign(moved) == np.sign(free.static_coordinates[lumbar]) and abs(moved) > np.radians(0.5)
    assert held.report.extra["calibration"].startswith("static") and held.report.limit_violations == 0


def test_static_pose_and_calibration_errors(body: BodyModel) -> None:
    run = read_trc(GAIT / "hamner_subject02_running.trc").between(0.0, 0.5)
    static = read_trc(GAIT / "hamner_subject02_static.trc")
    with pytest.raises(ValueError, match="pass the static trial"):
        fit_markers(run, model=body, static_pose=HAMNER_ANKLES)
    with pytest.raises(ValueError, match="static_pose"):
        fit_markers(run, static, model=body, calibration="motion")
    with pytest.raises(ValueError, match="'auto', 'static' or 'motion'"):
        fit_markers(run, static, model=body, calibration="static trial")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="needs the static trial"):
        fit_markers(run, model=body, calibration="static")
    with pytest.raises(UnknownCoordinateError, match="ankle_angle_r"):
        fit_markers(run, static, model=body, calibration="motion", static_pose={"ankle_r": 0.0})
    with pytest.raises(ValueError, match=r"ankle_angle_r = 1\.5 rad \(85\.9 degrees\) is outside"):
        fit_markers(run, static, model=body, calibration="motion", static_pose={"ankle_angle_r": 1.5})


def test_a_held_coordinate_moves_its_joints_child_and_the_bodies_below(body: BodyModel) -> None:
    skel = body.skeleton
    names = skel.body_names
    assert [names[b] for b in np.flatnonzero(moved_bodies(skel, ["ankle_angle_r"]))] == [
        "talus_r",
        "calcn_r",
        "toes_r",
    ]
    legs = {names[b] for b in np.flatnonzero(moved_bodies(skel, ["knee_angle_l", "hip_flexion_r"]))}
    assert {"femur_r", "tibia_r", "toes_r", "tibia_l", "toes_l"} <= legs
    assert not legs & {"femur_l", "pelvis", "torso"}
    plan = DofPlan.build(skel, GAIT2392)
    held = plan.holding(skel, {"knee_angle_r": 0.3})
    knee = skel.dof_index("knee_angle_r")
    assert knee in plan.free and knee not in held.free and held.locked[knee] == 0.3
    assert len(held.free) == len(plan.free) - 1 and np.array_equal(held.soft, plan.soft)


def test_write_outputs(gait_fit, body: BodyModel, tmp_path: Path) -> None:
    paths = gait_fit.write(tmp_path, body.skeleton.spec, "s01")
    cols, data, in_degrees = read_mot(paths["mot"])
    assert in_degrees and cols[0] == "time"
    np.testing.assert_allclose(
        np.radians(data[:, 1 : 1 + body.skeleton.n_dof]), gait_fit.coordinates, atol=1e-8
    )
    root = ET.parse(paths["osim"]).getroot()
    markers = {m.get("name"): m for m in root.iter("Marker")}
    assert set(markers) == set(gait_fit.markers.names)
    assert str(markers["R.ASIS"].findtext("socket_parent_frame")) == "/bodyset/pelvis"


@pytest.mark.opensim
def test_opensim_sees_our_markers_where_we_do(gait_fit, body: BodyModel, tmp_path: Path) -> None:
    opensim = pytest.importorskip("opensim")
    skel = body.skeleton
    model = opensim.Model(str(gait_fit.write(tmp_path, skel.spec)["osim"]))
    state = model.initSystem()
    k = 40
    for i, name in enumerate(skel.dof_names):
        model.getCoordinateSet().get(name).setValue(state, float(gait_fit.coordinates[k, i]), False)
    for j, name in enumerate(("pelvis_tx", "pelvis_ty", "pelvis_tz")):
        model.getCoordinateSet().get(name).setValue(state, float(gait_fit.root[k, j]), False)
    model.assemble(state)
    model.realizePosition(state)
    fk = skel.kinematics(torch.float64)
    chain = MarkerChain.build(fk, gait_fit.markers.body_indices(skel))
    ours = marker_positions(
        fk, chain, torch.as_tensor(gait_fit.markers.local), torch.as_tensor(gait_fit.coordinates[k : k + 1]),
        torch.as_tensor(gait_fit.root[k : k + 1]), torch.as_tensor(gait_fit.scales[None]),
    )[0].numpy()  # fmt: skip
    theirs = []
    for name in gait_fit.markers.names:
        p = model.getMarkerSet().get(name).getLocationInGround(state)
        theirs.append([p.get(0), p.get(1), p.get(2)])
    # OpenSim's assembly nudges coordinates sitting exactly on a clamped limit by ~1e-5 rad.
    np.testing.assert_allclose(np.array(theirs), ours, atol=2e-5)

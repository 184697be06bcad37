"""Mocap markers -> coordinates: accuracy against OpenSim's reference IK and speed against OpenSim's
InverseKinematicsTool, in one run.

What is measured
----------------
* Trials (OpenSim example data, ``tests/data/opensim_gait/SOURCES.md``): gait2392 subject01 walk (151
  frames at 60 Hz, calibrated from its static trial) and Hamner subject02 running (calibrated from 24
  frames of the motion, then the feet's markers placed from the subject's static trial with the ankles
  held at 0.5 degrees, as that pipeline's ``Setup_Scale.xml`` holds them: ``static_pose``; the full
  600-frame trial from ``../shared/data`` when present, else the 181-frame copy in ``tests/data``;
  ``--quick`` always uses the copy). ``ik_rmse_deg_hamner_motion_only``: the same trial calibrated from
  the motion alone, whose ankles read the constant offset of the feet's marker placement;
  ``ik_rmse_deg_hamner_static``: calibrated from its static trial (``calibration="static"``, ankles held).
* Weights: each trial is fitted with the marker weights of its reference's IK setup (``HAMNER_IK_WEIGHTS``,
  ``GAIT2392_IK_WEIGHTS``: the markers that IK leaves out get weight 0), so both solve the same objective.
* Accuracy: RMSE in degrees of our coordinates against OpenSim's reference ``*_ik.mot`` (gait2392 /
  Hamner2010 models) over the common time range, for every coordinate both have (knee sign flipped:
  those models flex negative). Also the mean difference and the RMSE with the mean removed, because a
  constant offset can come from differing marker definitions (Hamner2010's toe marker sits on the shoe,
  2.8 cm higher on the foot than gait2392's and ours: only the static trial's pose places it).
* Calibration (``ik_static_over_motion``): every fit with a static trial calibrates both from it and from
  the motion and reports both mean marker errors on the motion (``report.extra["calibration_choice"]``);
  the key is the worst ratio static / motion over the trials with a static trial: the two above and the
  Rajagopal walk with its static trial from ``../shared/data`` when present (fitted with ``auto``; the
  Rajagopal run, whose subject has no static trial there, is fitted from the motion only).
  ``upper_limb_at_limit_fraction``: frames an arm coordinate spends within 0.5 degrees of a limit.
* Observability (``ik_rmse_deg_max_observable``): the worst RMSE over the coordinates compared above that
  the fit does not report as unobservable (``report.extra["unobservable"]``, held near neutral);
  ``ik_rmse_deg_max_observable_offset_removed``: the same with each coordinate's mean difference removed
  (what is left once the two models' differing zeros and marker definitions are set aside).
* Speed: on the gait2392 walk, our ``fit_markers`` IK stage (all frames, staged and batched, after
  calibration; median of repeats) against ``opensim.InverseKinematicsTool`` run on our calibrated subject
  exported with ``write_osim`` and its MarkerSet, with the same marker weights, the same locked DOFs and
  our soft-DOF priors as IKCoordinateTasks (the same objective). ``ik_speed_ratio`` = OpenSim / ours.
* Agreement: the objective (weighted squared marker error + priors) of both solutions per frame, and,
  with the upper body locked in both, the lower-body coordinates of OpenSim's IK (accuracy 1e-7) against
  ours.

Usage::

    python benchmarks/fit_markers.py [--quick] [--json]
"""

from __future__ import annotations

import os
import platform
import statistics
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bodyfit.io.mocap import MarkerTrial, read_trc, write_trc
from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.mocap.calibration import DofPlan
from bodyfit.models.fitting.mocap.fitter import MarkerFit, fit_markers, observed_positions
from bodyfit.models.fitting.mocap.marker_sets import MARKER_SETS
from bodyfit.models.fitting.mocap.marker_solve import marker_errors, solve_ik
from bodyfit.models.skeleton.model import Skeleton
from bodyfit.models.skeleton.opensim_export import read_mot

ROOT = Path(__file__).resolve().parents[1]
LOCAL = ROOT / "tests" / "data" / "opensim_gait"
SHARED = ROOT.parent / "shared" / "data" / "opensim_gait"
FLEXION = [f"{j}_{s}" for s in ("r", "l") for j in ("hip_flexion", "knee_angle", "ankle_angle")]
ROOTS = ("pelvis_tx", "pelvis_ty", "pelvis_tz")
# The Hamner pipeline's Setup_Scale.xml holds the ankles at 0.00872665 rad in the static pose (weight 10).
HAMNER_STATIC_POSE = {"ankle_angle_r": 0.00872665, "ankle_angle_l": 0.00872665}
_CLUSTERS = ("Thigh.Upper", "Thigh.Front", "Thigh.Rear", "Shank.Upper", "Shank.Front", "Shank.Rear")
_FEET = ("Midfoot.Sup", "Midfoot.Lat", "Toe.Lat", "Toe.Med")
# The IK task weights of each reference (opensim-org/opensim-models): Pipelines/Hamner/Setup_IK.xml (no head
# markers, L.Bicep off) and Pipelines/Gait2392_Simbody/subject01_Setup_IK.xml (no arm or temple markers;
# its other weights are the gait2392 set's defaults).
HAMNER_IK_WEIGHTS = {
    "Sternum": 1.0, "V.Sacral": 50.0, "Top.Head": 0.0, "L.Bicep": 0.0, "R.Bicep": 10.0,
    **{f"{s}.{m}": w for s in "RL" for m, w in (
        ("ASIS", 50.0), ("Heel", 50.0), ("Toe.Tip", 50.0), ("Acromium", 10.0), ("Elbow", 20.0),
        ("Wrist.Med", 20.0), ("Wrist.Lat", 20.0), ("Temple", 0.0),
    )},
    **{f"{s}.{m}": 10.0 for s in "RL" for m in _CLUSTERS + _FEET},
}  # fmt: skip
GAIT2392_IK_WEIGHTS = {
    f"{s}.{m}": 0.0 for s in "RL" for m in ("Bicep", "Elbow", "Wrist.Med", "Wrist.Lat", "Temple")
}
LOWER_BODY = 17  # pelvis, legs: the first 17 DOFs of the skeleton
LEGS = ("pelvis", "femur", "tibia", "talus", "calcn", "toes", "patella")  # their bodies


def compare(fit: MarkerFit, skel: Skeleton, mot: Path) -> dict[str, dict[str, float]]:
    """Per coordinate both files have: RMSE, mean difference and RMSE without it (degrees)."""
    cols, data, _ = read_mot(mot)
    sel = (data[:, 0] >= fit.times[0] - 1e-9) & (data[:, 0] <= fit.times[-1] + 1e-9)
    out = {}
    for name in cols[1:]:
        if name not in skel.dof_names or np.ptp(data[sel, cols.index(name)]) < 1e-3:
            continue  # locked in the reference (subtalar, mtp, wrists): nothing to compare
        ours = np.degrees(np.interp(data[sel, 0], fit.times, fit.coordinates[:, skel.dof_index(name)]))
        diff = ours - data[sel, cols.index(name)] * (-1.0 if name.startswith("knee") else 1.0)
        out[name] = {
            "rmse": float(np.sqrt(np.mean(diff**2))),
            "mean": float(diff.mean()),
            "rmse_offset_removed": float(diff.std()),
        }
    return out


def _opensim_ik(
    fit: MarkerFit, skel: Skeleton, trial: MarkerTrial, folder: Path, lower_only: bool, accuracy: float = 1e-5
) -> tuple[np.ndarray, np.ndarray, float]:
    """OpenSim's IK on our exported subject: (q (T', n_dof), root (T', 3), seconds). ``accuracy``: the
    tool's convergence setting (1e-5 as in OpenSim's example setups)."""
    import opensim

    opensim.Logger.setLevelString("error")
    opensim.Logger.removeFileSink()  # no opensim.log in the working directory
    plan = DofPlan.build(skel, MARKER_SETS[fit.marker_set])
    name = "lower" if lower_only else "full"
    model = opensim.Model(str(fit.write(folder, skel.spec, f"subject_{name}")["osim"]))
    free = set(plan.free.tolist()) & (set(range(LOWER_BODY)) if lower_only else set(range(skel.n_dof)))
    for i, dof in enumerate(skel.dof_names):  # start where ours starts (the first frame's solution)
        coord = model.updCoordinateSet().get(dof)
        coord.setDefaultValue(float(fit.coordinates[0, i] if i in free else plan.locked[i]))
        coord.set_locked(i not in free)
    for j, dof in enumerate(ROOTS):
        model.updCoordinateSet().get(dof).setDefaultValue(float(fit.root[0, j]))
    model.initSystem()
    tasks = opensim.IKTaskSet()
    for marker, weight, body in zip(fit.markers.names, fit.markers.weights, fit.markers.bodies):
        if marker in trial.names and weight > 0 and (not lower_only or body.startswith(LEGS)):
            task = opensim.IKMarkerTask()
            task.setName(marker)
            task.setWeight(float(weight))
            tasks.cloneAndAppend(task)
    for i in sorted(free):
        if plan.soft[i] > 0:
            ctask = opensim.IKCoordinateTask()
            ctask.setName(skel.dof_names[i])
            ctask.setWeight(float(plan.soft[i]))
            ctask.setValueType(opensim.IKCoordinateTask.ManualValue)
            ctask.setValue(0.0)
            tasks.cloneAndAppend(ctask)
    tool = opensim.InverseKinematicsTool()
    tool.setModel(model)
    tool.getIKTaskSet().assign(tasks)
    trc = write_trc(folder / f"{name}.trc", trial)
    tool.setMarkerDataFileName(str(trc))
    tool.setStartTime(float(trial.times[0]))
    tool.setEndTime(float(trial.times[-1]))
    tool.setOutputMotionFileName(str(folder / f"{name}_ik.mot"))
    tool.set_accuracy(accuracy)
    tool.setResultsDir(str(folder))
    tool.set_report_errors(False)
    start = time.perf_counter()
    tool.run()
    seconds = time.perf_counter() - start
    cols, data, _ = read_mot(folder / f"{name}_ik.mot")
    q = np.stack([np.radians(data[:, cols.index(d)]) for d in skel.dof_names], axis=1)
    root = np.stack([data[:, cols.index(r)] for r in ROOTS], axis=1)
    return q, root, seconds


def _objective(
    fit: MarkerFit, skel: Skeleton, trial: MarkerTrial, q: np.ndarray, root: np.ndarray
) -> np.ndarray:
    """(T,) weighted squared marker error plus the soft-DOF priors (the IK objective)."""
    names = [n for n in fit.markers.names if n in trial.names]
    markers = fit.markers.subset(names)
    err = marker_errors(skel, markers, fit.scales, q, root, observed_positions(trial, names))
    plan = DofPlan.build(skel, MARKER_SETS[fit.marker_set])
    return np.nansum(markers.weights * err**2, axis=1) + (plan.soft * q**2).sum(axis=1)


def time_our_ik(fit: MarkerFit, skel: Skeleton, trial: MarkerTrial, repeats: int) -> float:
    """Median seconds of our IK stage (calibrated markers and scales, every frame of ``trial``)."""
    names = [n for n in fit.markers.names if n in trial.names]
    markers = fit.markers.subset(names)
    observed = observed_positions(trial, names)
    plan = DofPlan.build(skel, MARKER_SETS[fit.marker_set])
    times = []
    for _ in range(repeats + 1):
        start = time.perf_counter()
        solve_ik(skel, markers, fit.scales, observed, trial.times, plan)
        times.append(time.perf_counter() - start)
    return statistics.median(times[1:])


def run(quick: bool) -> dict[str, Any]:
    """The figures (see the module docstring); keys include ``ik_rmse_deg`` (trial -> coordinate ->
    degrees), ``ik_rmse_deg_max_flexion``, ``ik_rmse_deg_max_observable``, ``ik_static_over_motion``,
    ``ik_seconds``, ``opensim_ik_seconds``, ``ik_speed_ratio``."""
    model = BodyModel.load()
    skel = model.skeleton
    walk = read_trc(LOCAL / "gait2392_subject01_walk1.trc")
    static = read_trc(LOCAL / "gait2392_subject01_static.trc")
    hamner_dir = LOCAL if quick or not (SHARED / "hamner_subject02_running.trc").is_file() else SHARED
    run_trial = read_trc(hamner_dir / "hamner_subject02_running.trc")
    run_static = read_trc(LOCAL / "hamner_subject02_static.trc")
    run_mot = hamner_dir / "hamner_subject02_running_ik.mot"
    fits = {
        "gait2392_walk": (
            fit_markers(walk, static, model=model, calibration="static", weights=GAIT2392_IK_WEIGHTS),
            LOCAL / "gait2392_subject01_walk1_ik.mot",
        ),
        "hamner_running": (
            fit_markers(
                run_trial,
                run_static,
                model=model,
                weights=HAMNER_IK_WEIGHTS,
                calibration="motion",
                static_pose=HAMNER_STATIC_POSE,
            ),
            run_mot,
        ),
    }
    acc = {name: compare(fit, skel, mot) for name, (fit, mot) in fits.items()}
    motion_only = compare(fit_markers(run_trial, model=model, weights=HAMNER_IK_WEIGHTS), skel, run_mot)
    static_fit = fit_markers(
        run_trial,
        run_static,
        model=model,
        weights=HAMNER_IK_WEIGHTS,
        calibration="static",
        static_pose=HAMNER_STATIC_POSE,
    )
    static_cal = compare(static_fit, skel, run_mot)
    rmse = {name: {c: v["rmse"] for c, v in table.items()} for name, table in acc.items()}
    out: dict[str, Any] = {
        "ik_rmse_deg": rmse,
        "ik_rmse_deg_max_flexion": max(rmse[t][c] for t in rmse for c in FLEXION),
        "ik_rmse_deg_max_flexion_per_trial": {t: max(rmse[t][c] for c in FLEXION) for t in rmse},
        "ik_mean_difference_deg": {t: {c: v["mean"] for c, v in a.items()} for t, a in acc.items()},
        "ik_rmse_offset_removed_deg": {
            t: {c: v["rmse_offset_removed"] for c, v in a.items()} for t, a in acc.items()
        },
        "frames": {name: len(fit.times) for name, (fit, _) in fits.items()},
        "fit_seconds": {name: fit.report.seconds for name, (fit, _) in fits.items()},
        "marker_error_mm": {name: fit.report.distances.mean for name, (fit, _) in fits.items()},
        "limit_violations": {name: fit.report.limit_violations for name, (fit, _) in fits.items()},
        "hamner_source": "full trial" if hamner_dir == SHARED else "tests/data copy (0-3 s)",
        "ik_weights": "each reference's IK setup (Setup_IK.xml)",
        "hamner_calibration": fits["hamner_running"][0].report.extra["calibration"],
        "ik_rmse_deg_hamner_motion_only": {c: v["rmse"] for c, v in motion_only.items()},
        "ik_rmse_deg_hamner_static": {c: v["rmse"] for c, v in static_cal.items()},
        "marker_error_mm_hamner_static": static_fit.report.distances.mean,
    }
    out.update(_whole_body(fits, acc, model))
    gait_fit = fits["gait2392_walk"][0]
    timed = walk.between(0.0, 1.0) if quick else walk
    out["ik_seconds"] = time_our_ik(gait_fit, skel, timed, repeats=1 if quick else 3)
    out["ik_frames_timed"] = timed.n_frames
    try:
        import opensim  # noqa: F401
    except ImportError:
        out.update(opensim_ik_seconds=None, ik_speed_ratio=None, opensim="not installed")
        return out | _machine()
    n = timed.n_frames
    sub = replace(gait_fit, coordinates=gait_fit.coordinates[:n], root=gait_fit.root[:n], times=timed.times)
    with tempfile.TemporaryDirectory() as tmp:
        q_os, root_os, seconds = _opensim_ik(sub, skel, timed, Path(tmp), lower_only=False)
        ours_cost = _objective(sub, skel, timed, sub.coordinates, sub.root)
        their_cost = _objective(sub, skel, timed, q_os, root_os)
        out["opensim_ik_seconds"] = seconds
        out["ik_speed_ratio"] = seconds / out["ik_seconds"]
        out["objective_ours_over_opensim"] = float(np.median(ours_cost / their_cost))
        out["frames_where_opensim_objective_lower"] = int((their_cost < ours_cost - 1e-12).sum())
        if not quick:
            lower = fit_markers(walk, static, model=model, weights=_upper_body_off(gait_fit))
            q_low, _, _ = _opensim_ik(lower, skel, walk, Path(tmp), lower_only=True, accuracy=1e-7)
            diff = np.degrees(q_low[:, :LOWER_BODY] - lower.coordinates[:, :LOWER_BODY])
            out["lower_body_agreement_rmse_deg"] = {
                skel.dof_names[i]: float(np.sqrt(np.mean(diff[:, i] ** 2)))
                for i in range(LOWER_BODY)
                if "subtalar" not in skel.dof_names[i] and "mtp" not in skel.dof_names[i]
            }
    return out | _machine()


def _whole_body(
    fits: dict[str, tuple[MarkerFit, Path]], acc: dict[str, dict[str, dict[str, float]]], model: BodyModel
) -> dict[str, Any]:
    """Static against motion calibration on every trial with a static trial (the Rajagopal walk from
    ``../shared/data`` when present; its run has no static trial of its subject, so it is fitted from the
    motion only), and the worst RMSE over the coordinates the marker set observes."""
    extra: dict[str, MarkerFit] = {}
    if (SHARED / "rajagopal_static_walk_1.trc").is_file():
        raj_static = read_trc(SHARED / "rajagopal_static_walk_1.trc")
        extra["rajagopal_walk"] = fit_markers(
            read_trc(SHARED / "rajagopal_motion_capture_walk.trc"), raj_static, model=model
        )
        extra["rajagopal_run"] = fit_markers(
            read_trc(SHARED / "rajagopal_motion_capture_run.trc"), model=model
        )
    every = {name: fit for name, (fit, _) in fits.items()} | extra
    errors = {name: fit.report.extra["calibration_choice"]["marker_error_mm"] for name, fit in every.items()}
    ratios = {name: e["static"] / e["motion"] for name, e in errors.items() if "static" in e}
    observable = {
        trial: {
            c: v["rmse"] for c, v in table.items() if c not in fits[trial][0].report.extra["unobservable"]
        }
        for trial, table in acc.items()
    }
    worst = {trial: max(table, key=lambda c: table[c]) for trial, table in observable.items()}
    flat = {
        trial: max(acc[trial][c]["rmse_offset_removed"] for c in table) for trial, table in observable.items()
    }
    skel = model.skeleton
    return {
        "ik_static_over_motion": max(ratios.values()),
        "ik_static_over_motion_per_trial": ratios,
        "calibration_marker_error_mm": errors,
        "calibration_chosen": {n: f.report.extra["calibration_choice"]["chosen"] for n, f in every.items()},
        "ik_rmse_deg_max_observable": max(observable[t][c] for t, c in worst.items()),
        "ik_rmse_deg_max_observable_per_trial": {t: [c, observable[t][c]] for t, c in worst.items()},
        "ik_rmse_deg_max_observable_offset_removed": max(flat.values()),
        "unobservable": {name: sorted(f.report.extra["unobservable"]) for name, f in every.items()},
        "upper_limb_at_limit_fraction": {name: _at_limits(f, skel) for name, f in every.items()},
        "marker_error_mm_all": {name: f.report.distances.mean for name, f in every.items()},
    }


UPPER_LIMB = ("arm_flex", "arm_add", "arm_rot", "elbow_flex", "pro_sup")


def _at_limits(fit: MarkerFit, skel: Skeleton) -> dict[str, float]:
    """Fraction of frames each upper-limb coordinate spends within 0.5 degrees of a joint limit (only the
    coordinates that do so in some frame)."""
    out = {}
    for i, name in enumerate(skel.dof_names):
        if name.startswith(UPPER_LIMB) and name not in fit.report.extra["unobservable"]:
            near = np.abs(fit.coordinates[:, i, None] - skel.ranges[i][None]).min(axis=1) < np.radians(0.5)
            if near.any():
                out[name] = float(near.mean())
    return out


def _upper_body_off(fit: MarkerFit) -> dict[str, float]:
    """Weights that drop the markers above the pelvis and legs (for the lower-body agreement check)."""
    return {n: 0.0 for n, b in zip(fit.markers.names, fit.markers.bodies) if not b.startswith(LEGS)}


def _machine() -> dict[str, Any]:
    return {
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "torch_version": torch.__version__,
    }


def show(res: dict[str, Any]) -> None:
    """The figures as tables, one per trial."""
    for trial, table in res["ik_rmse_deg"].items():
        print(f"\n{trial}: RMSE vs OpenSim reference IK (deg)   [mean difference, RMSE offset removed]")
        for coord, value in table.items():
            mean = res["ik_mean_difference_deg"][trial][coord]
            flat = res["ik_rmse_offset_removed_deg"][trial][coord]
            mark = "  <- target 5" if coord in FLEXION else ""
            print(f"  {coord:20s} {value:6.2f}   [{mean:+6.2f}, {flat:5.2f}]{mark}")
    worst = res["ik_rmse_deg_max_flexion_per_trial"]
    print(f"\nmax flexion RMSE: {res['ik_rmse_deg_max_flexion']:.2f} deg  {worst}")
    print(f"marker error (mm): {res['marker_error_mm']}; limit violations: {res['limit_violations']}")
    ratio = res.get("ik_speed_ratio") or float("nan")
    theirs = res.get("opensim_ik_seconds") or float("nan")
    print(
        f"IK on {res['ik_frames_timed']} frames: ours {res['ik_seconds']:.3f} s, OpenSim {theirs:.3f} s, "
        f"OpenSim / ours = {ratio:.1f}x"
    )
    if "objective_ours_over_opensim" in res:
        print(
            f"objective ours / OpenSim (median over frames): {res['objective_ours_over_opensim']:.3f}; "
            f"frames where OpenSim's is lower: {res['frames_where_opensim_objective_lower']}"
        )
    if "lower_body_agreement_rmse_deg" in res:
        print(f"lower body, OpenSim IK vs ours (deg RMSE): {res['lower_body_agreement_rmse_deg']}")


def main(argv: list[str] | None = None) -> None:
    from bench_cli import bench_main  # benchmarks/ is on sys.path when this runs as a script

    bench_main(
        run,
        "mocap markers -> coordinates against OpenSim's reference IK and its InverseKinematicsTool",
        "the 3 s running copy, 1 s of walking timed",
        argv,
        show,
    )


if __name__ == "__main__":
    main()

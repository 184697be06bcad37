"""A matrix of whole-body poses x scan corruptions for raw-scan fits, each fitted with the orientation
searched and with it hinted: the fits that :mod:`calibrate_quality` calibrates the quality estimate on,
and that :mod:`fit_confidence` measures it (and the gross-failure rate) with, on other seeds.

Bodies are held-out anny adults (a seed the asset build never used) posed by anny's own rig to one of
:data:`POSES` (each a set of coordinates in degrees, jittered per body), in our topology: ground truth the
model never saw. Each body's surface is sampled (:data:`POINTS` points, fewer with ``points=``) and corrupted
by one of :data:`CORRUPTIONS` with the generators of ``corrupt.py`` and ``fit_scans.py``; the scan is then
moved rigidly (an upright body turned about the vertical, unless the corruption turns it otherwise).

Per fit a row records the pose, corruption, mode, the true registration error (mean vertex distance of the
registration to the true body, mm), the largest joint error (mm) and the fit's report, shape and
coordinates, from which :func:`bodyfit.models.fitting.common.quality.scan_features` reads the features again.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import corrupt  # benchmarks/ is on sys.path when this runs as a script
import fit_scans
import numpy as np
import torch

from bodyfit.io.scans import sample_surface, scan_from_arrays
from bodyfit.models.body.anny_posed import pose_anny, template_landmarks
from bodyfit.models.body.anny_source import AnnySource
from bodyfit.models.body.model import BodyModel
from bodyfit.models.body.skeleton_fit import place_skeletons
from bodyfit.models.build_assets import default_cache_dir
from bodyfit.models.errors import BodyfitError
from bodyfit.models.fitting.scan.config import ScanFitConfig
from bodyfit.models.fitting.scan.fitter import ScanFitter
from bodyfit.models.threads import torch_threads

POINTS = 30_000
JITTER_DEG = 4.0  # every coordinate of a pose, per body (normal, clipped to its range)
GROSS_MEAN_MM = 15.0  # a gross failure: mean registration error above this ...
GROSS_JOINT_MM = 50.0  # ... or a joint farther than this from the true one
FLOOR_FRACTION = fit_scans.FLOOR_FRACTION

_ARMS = ("r", "l")


def _both(**degrees: float) -> dict[str, float]:
    """The same coordinates on both sides: ``arm_add=-90`` -> arm_add_r and arm_add_l."""
    return {f"{k}_{s}": v for k, v in degrees.items() for s in _ARMS}


# Poses: coordinates in degrees over the bind pose (abduction is negative arm_add; a full raise of the arm
# takes the scapula's upward rotation and elevation on top of the glenohumeral range).
POSES: dict[str, dict[str, float]] = {
    "a_pose": {},
    "t_pose": _both(arm_add=-90.0, elbow_flex=5.0, scapula_upward_rot=15.0),
    "arms_raised": _both(arm_add=-120.0, scapula_upward_rot=50.0, scapula_elevation=20.0, elbow_flex=10.0),
    "arms_forward_up": _both(
        arm_flex=90.0, arm_add=-10.0, scapula_upward_rot=50.0, scapula_elevation=15.0, elbow_flex=10.0
    ),
    "crossed_arms": _both(arm_flex=45.0, arm_add=30.0, elbow_flex=120.0),
    "hands_on_hips": _both(arm_add=-45.0, arm_flex=-15.0, elbow_flex=100.0),
    "crouching": _both(arm_flex=30.0, elbow_flex=30.0)
    | {"hip_flexion_r": 110.0, "hip_flexion_l": 110.0, "knee_angle_r": 110.0, "knee_angle_l": 110.0}
    | {"ankle_angle_r": 25.0, "ankle_angle_l": 25.0},
    "sitting": {"hip_flexion_r": 85.0, "hip_flexion_l": 85.0, "knee_angle_r": 85.0, "knee_angle_l": 85.0},
    "lying": {"pelvis_tilt": 90.0},
    "walking": {"hip_flexion_r": 25.0, "hip_flexion_l": -10.0, "knee_angle_r": 10.0, "knee_angle_l": 40.0}
    | {"arm_flex_r": -25.0, "arm_flex_l": 25.0, "elbow_flex_r": 20.0, "elbow_flex_l": 35.0}
    | _both(arm_add=-12.0),
    "random": {},  # uniform within 30% of every range about its middle, as fit_scans.py
}
CORRUPTIONS = (
    "clean",
    "upside_down",
    "rotated",
    "millimetres",
    "front_half",
    "back_half",
    "voxels_2cm",
    "floor",
    "noise_outliers",
    "depth",
    "holes",
    "clothing",
)
MODES = ("searched", "hinted")


def pose_coordinates(model: BodyModel, pose: str, rng: np.random.Generator) -> np.ndarray:
    """(n_dof,) radians: ``pose`` of :data:`POSES` over the bind pose, every coordinate but the pelvis's
    jittered by :data:`JITTER_DEG`, inside the ranges."""
    skel = model.skeleton
    lo, hi = skel.ranges[:, 0], skel.ranges[:, 1]
    if pose == "random":
        q = 0.5 * (lo + hi) + 0.15 * (hi - lo) * rng.uniform(-1.0, 1.0, skel.n_dof)
    else:
        q = skel.inside(model.bind_coordinates, 0.1).copy()
        for name, value in POSES[pose].items():
            q[skel.dof_index(name)] = math.radians(value)
    q[3:] += np.radians(JITTER_DEG) * rng.normal(size=skel.n_dof - 3)
    if pose != "lying":
        q[:3] = 0.0
    return np.clip(q, lo + 1e-3, hi - 1e-3)


@dataclass(frozen=True)
class Bodies:
    """Posed held-out bodies: vertices (n, V, 3) and joints (n, J, 3) in our frame (+X forward, +Y up),
    metres; q (n, n_dof); pelvis (n, 3, 3): each pelvis's orientation in that frame (the body's own axes:
    upright but for a lying body)."""

    vertices: np.ndarray
    joints: np.ndarray
    q: np.ndarray
    pelvis: np.ndarray


def posed_bodies(model: BodyModel, q: np.ndarray, seed: int) -> Bodies:
    """len(q) anny adults sampled with ``seed`` (one the asset build never used), posed to q (n, n_dof) by
    anny's rig, with their true joint centres (the model's anatomical joints of the skeleton placed inside
    each body)."""
    src = AnnySource(default_cache_dir())
    n = len(q)
    pop = src.sample(n, seed)
    landmarks, _ = template_landmarks(src)
    placed = place_skeletons(model.skeleton, src.rest(pop)["vertices"][:, landmarks], 150)
    fk = model.skeleton.kinematics(torch.float64)
    frames_a = fk(
        torch.as_tensor(placed.q), torch.as_tensor(placed.root), torch.as_tensor(placed.scales)
    ).frames
    with torch_threads(2):
        vertices, frames = pose_anny(src, pop, model.skeleton, placed, np.arange(n), q, frames_a)
    joints = model.decoder(torch.float64).joints(frames, torch.as_tensor(placed.scales))
    pelvis = frames[:, model.skeleton.body_names.index("pelvis"), :3, :3].numpy()
    return Bodies(np.asarray(vertices, np.float64), joints.numpy(), q, pelvis)


def _turn(angle: float, axis: int) -> np.ndarray:
    """(3, 3) rotation by ``angle`` radians about coordinate axis ``axis``."""
    c, s = math.cos(angle), math.sin(angle)
    i, j = [a for a in range(3) if a != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def motion(corruption: str, rng: np.random.Generator) -> np.ndarray:
    """(4, 4) the rigid motion from our frame to the scan's: turned about the vertical (Y) and moved up to
    1 m; ``upside_down`` also turned over, ``rotated`` by a random rotation (``corrupt.random_rigid``)."""
    if corruption == "rotated":
        return corrupt.random_rigid(np.zeros((1, 3)), rng)[1]
    T = np.eye(4)
    T[:3, :3] = _turn(rng.uniform(-math.pi, math.pi), 1)
    if corruption == "upside_down":
        T[:3, :3] = T[:3, :3] @ _turn(math.pi, 0)
    direction = rng.normal(size=3)
    T[:3, 3] = direction / np.linalg.norm(direction) * rng.uniform(0.0, 1.0)
    return T


def _floor(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``points`` (N, 3) with a 2.5 m square floor under their lowest point (+Y up) holding
    :data:`FLOOR_FRACTION` of all."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    n = round(FLOOR_FRACTION * len(points) / (1.0 - FLOOR_FRACTION))
    floor = 0.5 * (lo + hi) + rng.uniform(-1.25, 1.25, (n, 3))
    floor[:, 1] = lo[1]
    return np.concatenate([points, floor])


def _voxels(points: np.ndarray, size: float) -> np.ndarray:
    """The mean point (M, 3) of each ``size`` cube that holds points (N, 3): a coarse scanner's grid."""
    _, cell, count = np.unique(np.floor(points / size), axis=0, return_inverse=True, return_counts=True)
    cell = cell.ravel()
    sums = np.zeros((len(count), 3))
    np.add.at(sums, cell, points)
    return sums / count[:, None]


def corrupted_points(
    vertices: np.ndarray,
    faces: np.ndarray,
    corruption: str,
    seed: int,
    points: int = POINTS,
    facing: np.ndarray | None = None,
) -> np.ndarray:
    """(N, 3) scan points of one body (V, 3; +X forward, +Y up), metres, under ``corruption`` of
    :data:`CORRUPTIONS`, before the rigid motion (:func:`motion`) and the change of units. ``facing`` (3,)
    is the unit direction the body's front faces (+X when None): ``front_half`` keeps the surface that
    faces that way (outward normal within 90 degrees of it), ``back_half`` the surface that faces away, as
    a scanner sweeping half a turn around the body sees it: every limb keeps its visible side, and a lying
    body's halves are its front and back, not its head and feet ends. (A plane through the body's centre
    would take whole limbs away, which no sensor does and no fit can place.)"""
    rng = np.random.default_rng(seed)
    if corruption in ("depth", "holes", "clothing"):
        p = fit_scans.make_scan(vertices, faces, corruption, seed)
        return p if corruption == "depth" else p[rng.permutation(len(p))[: round(points * len(p) / 1e5)]]
    dense = 2 * points if corruption in ("front_half", "back_half", "voxels_2cm") else points
    p, normals = sample_surface(vertices, faces, dense, seed)
    forward = normals @ (np.array([1.0, 0.0, 0.0]) if facing is None else facing)
    if corruption == "front_half":
        return p[forward > 0.0]
    if corruption == "back_half":
        return p[forward < 0.0]
    if corruption == "voxels_2cm":
        return _voxels(p, 0.02)
    if corruption == "floor":
        return _floor(p, rng)
    if corruption == "noise_outliers":
        return corrupt.add_outliers(corrupt.add_noise(p, 0.005, rng), 0.05, rng)[0]
    return p


@dataclass(frozen=True)
class Case:
    """One fit of the matrix: ``body`` (index into the bodies), its pose and corruption, the mode
    (orientation "searched" or "hinted") and the seed of its scan."""

    body: int
    pose: str
    corruption: str
    mode: str
    seed: int


def fit_case(fitter: ScanFitter, model: BodyModel, bodies: Bodies, case: Case, points: int) -> dict[str, Any]:
    """Scan, move and fit ``case``; its row: the true registration error (mm), each joint's error and the
    largest (mm), gross or not, and the fit's report (``to_dict``), shape and coordinates; a scan the
    fitter refuses is a gross failure whose row holds the message (``error``) instead."""
    truth, joints = bodies.vertices[case.body], bodies.joints[case.body]
    raw = corrupted_points(
        truth, model.faces, case.corruption, case.seed, points, bodies.pelvis[case.body][:, 0]
    )
    T = motion(case.corruption, np.random.default_rng(case.seed + 1))
    moved = raw @ T[:3, :3].T + T[:3, 3]
    scale = 1000.0 if case.corruption == "millimetres" else 1.0
    scan = scan_from_arrays(moved * scale, units="auto")
    # the hint is what ScanFitter.fit(orientation=) takes: the scan's axes to the body's own
    orientation = (T[:3, :3] @ bodies.pelvis[case.body]).T if case.mode == "hinted" else None
    began = time.perf_counter()
    head = {"pose": case.pose, "corruption": case.corruption, "mode": case.mode, "seed": case.seed}
    try:
        with torch_threads(1):
            fit = fitter.fit(scan, orientation=orientation)
    except BodyfitError as exc:  # refused (e.g. no person found): a gross failure with no report
        return {**head, "points": len(moved), "gross": True, "error": str(exc)}
    seconds = time.perf_counter() - began
    vertex_error = np.linalg.norm(fit.registration - (truth @ T[:3, :3].T + T[:3, 3]), axis=1) * 1000
    joint_error = np.linalg.norm(fit.joints - (joints @ T[:3, :3].T + T[:3, 3]), axis=1) * 1000
    registration, joint_max = float(vertex_error.mean()), float(joint_error.max())
    return {
        **head,
        "points": len(moved),
        "registration_mm": registration,
        "joint_max_mm": joint_max,
        "joint_mm": [round(float(e), 1) for e in joint_error],
        "gross": bool(registration > GROSS_MEAN_MM or joint_max > GROSS_JOINT_MM),
        "seconds": seconds,
        "report": fit.report.to_dict(),
        "shape": fit.shape.tolist(),
        "coordinates": fit.coordinates.tolist(),
    }


def cases(
    poses: tuple[str, ...], corruptions: tuple[str, ...], seed: int, cells: Callable[[int, int], bool]
) -> list[Case]:
    """Every (pose, corruption) cell that ``cells(pose index, corruption index)`` keeps, in both modes, one
    body per cell (the bodies in :func:`pose_coordinates` order: pose-major), scan seeds from ``seed``; in
    an order shuffled by ``seed``, so that the first fits of a run already cover the matrix."""
    out = []
    for i, pose in enumerate(poses):
        for j, corruption in enumerate(corruptions):
            if cells(i, j):
                body = i * len(corruptions) + j
                out += [Case(body, pose, corruption, mode, seed + 10 * body) for mode in MODES]
    return [out[k] for k in np.random.default_rng(seed).permutation(len(out))]


def run_matrix(
    poses: tuple[str, ...], corruptions: tuple[str, ...], seed: int, points: int,
    cells: Callable[[int, int], bool] = lambda i, j: True,
) -> Iterator[dict[str, Any]]:  # fmt: skip
    """The rows of the matrix (:func:`cases`), one held-out body per cell (sampled with ``seed``), as each
    fit ends; one process, one torch thread."""
    model = BodyModel.load()
    rng = np.random.default_rng(seed)
    chosen = cases(poses, corruptions, seed, cells)
    q = np.stack([pose_coordinates(model, p, rng) for p in poses for _ in corruptions])
    bodies = posed_bodies(model, q, seed)
    fitter = ScanFitter(model, ScanFitConfig(processes=1))
    try:
        for case in chosen:
            yield {"body": case.body, **fit_case(fitter, model, bodies, case, points)}
    finally:
        fitter.close()

"""Bony landmarks named on the template skin, and the joint centres biomechanics derives from them.

Landmarks are template vertex indices: every body of the model shares the topology, so a landmark is
the same vertex on every body. They are picked once, at build time, on the mean body: each definition
gives an approximate position (metres, our frame, right side for bilateral landmarks) and an outward
direction; the landmark is the vertex furthest along that direction within ``radius`` of the position.
Left landmarks are the mirror vertices of the right ones.

Joint centres from landmarks (all positions in metres):

- hip: regression of M. E. Harrington, A. B. Zavatsky, S. E. M. Lawson, Z. Yuan and T. N. Theologis,
  "Prediction of the hip joint centre in adults, children, and patients with cerebral palsy based on magnetic
  resonance imaging", Journal of Biomechanics 40(3), 2007, on pelvis width (PW, inter-ASIS
  distance) and depth (PD, mid-ASIS to mid-PSIS): posterior 0.24 PD + 9.9 mm, inferior 0.30 PW + 10.9 mm,
  lateral 0.33 PW + 7.3 mm from the mid-ASIS point, in the pelvis frame.
- pelvis origin: mid-ASIS point (the origin of Rajagopal's pelvis, as in Delp's lower-limb models).
- knee: mid-point of the femoral epicondyles (E. S. Grood and W. J. Suntay, "A joint coordinate system for
  the clinical description of three-dimensional motions: application to the knee", Journal of Biomechanical
  Engineering 105(2), 1983; Wu et al. 2002, below).
- ankle: mid-point of the malleoli (G. Wu et al., "ISB recommendation on definitions of joint coordinate
  system of various joints for the reporting of human joint motion - part I: ankle, hip, and spine", Journal
  of Biomechanics 35(4), 2002).
- metatarsophalangeal: mid-point of the first and fifth metatarsal heads (A. Leardini, M. G. Benedetti,
  L. Berti, D. Bettinelli, R. Nativo and S. Giannini, "Rear-foot, mid-foot and fore-foot motion during the
  stance phase of gait", Gait & Posture 25(3), 2007).
- shoulder (glenohumeral): below the acromion by 17% of the inter-acromion distance (G. Rab, K. Petuskey and
  A. Bagley, "A method for determination of upper extremity kinematics", Gait & Posture 15(2), 2002).
- elbow: mid-point of the humeral epicondyles; wrist: mid-point of the radial and ulnar styloids (G. Wu et
  al., "ISB recommendation on definitions of joint coordinate systems of various joints for the reporting of
  human joint motion - Part II: shoulder, elbow, wrist and hand", Journal of Biomechanics 38(5), 2005).
- cervicothoracic (C7/T1): from C7 towards the suprasternale (jugular notch), 55% of the C7-suprasternale
  distance along a line rotated 8 degrees downward from it (M. P. Reed, M. A. Manary and L. W. Schneider,
  "Methods for Measuring and Representing Automobile Occupant Posture", SAE Technical Paper 1999-01-0959,
  1999).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LandmarkDef:
    """How a landmark is found on the mean body.

    ``position`` is the approximate location (right side for bilateral landmarks), ``direction`` the
    outward direction; ``perpendicular_to`` optionally names two other positions whose axis the direction
    is made perpendicular to (for limbs that are not aligned with the world axes).
    """

    name: str
    position: tuple[float, float, float]
    direction: tuple[float, float, float]
    radius: float = 0.03
    bilateral: bool = True


# Approximate positions on anny's mean body (all six phenotypes 0.5) in its rest A-pose, our frame.
LANDMARKS: tuple[LandmarkDef, ...] = (
    # pelvis and thigh
    LandmarkDef("ASIS", (0.10, 0.09, 0.105), (1.0, 0.0, 0.3)),
    LandmarkDef("PSIS", (-0.08, 0.07, 0.045), (-1.0, 0.0, 0.0), 0.025),
    LandmarkDef("iliac_crest", (0.02, 0.15, 0.15), (0.0, 0.3, 1.0)),
    LandmarkDef("greater_trochanter", (0.02, 0.0, 0.165), (0.0, 0.0, 1.0), 0.04),
    LandmarkDef("lateral_femoral_epicondyle", (0.04, -0.35, 0.17), (0.0, 0.0, 1.0), 0.04),
    LandmarkDef("medial_femoral_epicondyle", (0.04, -0.35, 0.09), (0.0, 0.0, -1.0), 0.04),
    LandmarkDef("patella", (0.09, -0.32, 0.135), (1.0, 0.0, 0.0), 0.04),
    LandmarkDef("tibial_tuberosity", (0.08, -0.41, 0.14), (1.0, 0.0, 0.0), 0.03),
    # ankle and foot
    LandmarkDef("lateral_malleolus", (-0.005, -0.76, 0.20), (0.0, 0.0, 1.0), 0.03),
    LandmarkDef("medial_malleolus", (0.005, -0.745, 0.15), (0.0, 0.0, -1.0), 0.03),
    LandmarkDef("heel", (-0.06, -0.80, 0.175), (-1.0, -0.2, 0.0), 0.04),
    LandmarkDef("first_metatarsal_head", (0.13, -0.80, 0.14), (0.0, 0.0, -1.0), 0.03),
    LandmarkDef("fifth_metatarsal_head", (0.09, -0.805, 0.215), (0.0, 0.0, 1.0), 0.03),
    LandmarkDef("toe_tip", (0.20, -0.80, 0.15), (1.0, 0.0, 0.0), 0.06),
    # shoulder and arm
    LandmarkDef("acromion", (0.01, 0.52, 0.17), (0.0, 1.0, 0.6), 0.04),
    LandmarkDef("lateral_humeral_epicondyle", (0.02, 0.29, 0.35), (0.0, 0.6, 0.8), 0.04),
    LandmarkDef("medial_humeral_epicondyle", (0.02, 0.27, 0.31), (0.0, -0.6, -0.8), 0.04),
    LandmarkDef("radial_styloid", (0.175, 0.17, 0.44), (0.0, 0.6, -0.5), 0.03),
    LandmarkDef("ulnar_styloid", (0.175, 0.16, 0.45), (0.0, -0.6, 0.5), 0.03),
    LandmarkDef("dactylion", (0.32, 0.03, 0.50), (0.6, -0.6, 0.4), 0.08),
    # head
    LandmarkDef("tragion", (0.05, 0.69, 0.07), (0.0, 0.0, 1.0), 0.03),
    # midline
    LandmarkDef("C7", (-0.035, 0.545, 0.0), (-1.0, 0.4, 0.0), 0.03, bilateral=False),
    LandmarkDef("suprasternale", (0.075, 0.495, 0.0), (1.0, 0.0, 0.0), 0.02, bilateral=False),
    LandmarkDef("xiphoid", (0.12, 0.33, 0.0), (1.0, 0.0, 0.0), 0.03, bilateral=False),
    LandmarkDef("omphalion", (0.11, 0.13, 0.0), (1.0, 0.0, 0.0), 0.04, bilateral=False),
    LandmarkDef("vertex", (0.0, 0.85, 0.0), (0.0, 1.0, 0.0), 0.08, bilateral=False),
    LandmarkDef("pronasale", (0.14, 0.66, 0.0), (1.0, 0.0, 0.0), 0.04, bilateral=False),
)


def landmark_names() -> list[str]:
    """Names in storage order: bilateral landmarks as ``<name>_r``, ``<name>_l``; midline ones plain."""
    names: list[str] = []
    for d in LANDMARKS:
        names += [f"{d.name}_r", f"{d.name}_l"] if d.bilateral else [d.name]
    return names


def mirror_map(vertices: np.ndarray, tolerance: float = 2e-3) -> np.ndarray:
    """Index of each vertex's mirror image (z -> -z).

    Args:
        vertices: (V, 3) a left-right symmetric mesh.
    Returns:
        (V,) permutation ``m`` with ``vertices[m] ~ vertices * (1, 1, -1)``.
    Raises:
        ValueError: if the mesh is not symmetric within ``tolerance`` metres.
    """
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(vertices).query(vertices * np.array([1.0, 1.0, -1.0]))
    if dist.max() > tolerance or len(np.unique(idx)) != len(idx):
        raise ValueError(f"template is not left-right symmetric (worst mirror gap {dist.max() * 1e3:.2f} mm)")
    return np.asarray(idx, np.int64)


def pick_landmarks(vertices: np.ndarray, mirror: np.ndarray) -> np.ndarray:
    """Landmark vertex indices on the mean body, in :func:`landmark_names` order.

    Args:
        vertices: (V, 3) mean-body rest vertices in our frame.
        mirror: (V,) from :func:`mirror_map`.
    Returns:
        (L,) int64 vertex indices.
    """
    out: list[int] = []
    for d in LANDMARKS:
        p = np.asarray(d.position)
        near = np.flatnonzero(np.linalg.norm(vertices - p, axis=1) < d.radius)
        if d.bilateral is False:
            near = near[np.abs(vertices[near, 2]) < 0.004]
        if len(near) == 0:
            raise ValueError(f"no template vertex within {d.radius} m of landmark {d.name!r} at {p}")
        direction = np.asarray(d.direction) / np.linalg.norm(d.direction)
        best = int(near[np.argmax(vertices[near] @ direction)])
        out += [best, int(mirror[best])] if d.bilateral else [best]
    return np.asarray(out, np.int64)


def _pair(L: np.ndarray, names: list[str], name: str) -> tuple[np.ndarray, np.ndarray]:
    return L[:, names.index(f"{name}_r")], L[:, names.index(f"{name}_l")]


def joint_targets(L: np.ndarray, names: list[str]) -> dict[str, np.ndarray]:
    """Joint centres from landmark positions by the rules in this module's docstring.

    Args:
        L: (N, n_landmark, 3) landmark positions (our frame) of N bodies.
        names: landmark names of axis 1.
    Returns:
        name -> (N, 3): ``pelvis``, ``hip_r/l``, ``knee_r/l``, ``ankle_r/l``, ``mtp_r/l``,
        ``shoulder_r/l``, ``elbow_r/l``, ``wrist_r/l``, ``cervicothoracic``.
    """
    asis_r, asis_l = _pair(L, names, "ASIS")
    psis_r, psis_l = _pair(L, names, "PSIS")
    origin = 0.5 * (asis_r + asis_l)
    z = _unit(asis_r - asis_l)
    back = 0.5 * (psis_r + psis_l)
    x = _unit(_reject(origin - back, z))
    y = np.cross(z, x)
    pw = np.linalg.norm(asis_r - asis_l, axis=-1, keepdims=True)
    pd = np.sum((origin - back) * x, axis=-1, keepdims=True)
    out = {"pelvis": origin}
    for side, sign in (("r", 1.0), ("l", -1.0)):
        out[f"hip_{side}"] = (
            origin - (0.24 * pd + 0.0099) * x - (0.30 * pw + 0.0109) * y + sign * (0.33 * pw + 0.0073) * z
        )
    mids = {
        "knee": ("lateral_femoral_epicondyle", "medial_femoral_epicondyle"),
        "ankle": ("lateral_malleolus", "medial_malleolus"),
        "mtp": ("first_metatarsal_head", "fifth_metatarsal_head"),
        "elbow": ("lateral_humeral_epicondyle", "medial_humeral_epicondyle"),
        "wrist": ("radial_styloid", "ulnar_styloid"),
    }
    for joint, (a, b) in mids.items():
        for side in ("r", "l"):
            out[f"{joint}_{side}"] = 0.5 * (
                L[:, names.index(f"{a}_{side}")] + L[:, names.index(f"{b}_{side}")]
            )
    acr_r, acr_l = _pair(L, names, "acromion")
    width = np.linalg.norm(acr_r - acr_l, axis=-1, keepdims=True)
    out["shoulder_r"] = acr_r - 0.17 * width * y
    out["shoulder_l"] = acr_l - 0.17 * width * y
    c7, ss = L[:, names.index("C7")], L[:, names.index("suprasternale")]
    # Rotate the C7 -> suprasternale vector 8 degrees downward about the body's left-right axis.
    v = ss - c7
    angle = np.deg2rad(8.0)
    axis = -z  # positive rotation about -z turns a forward vector downward
    v_rot = (
        v * np.cos(angle)
        + np.cross(axis, v) * np.sin(angle)
        + axis * np.sum(axis * v, -1, keepdims=True) * (1 - np.cos(angle))
    )
    out["cervicothoracic"] = c7 + 0.55 * v_rot
    return out


def axis_targets(L: np.ndarray, names: list[str]) -> dict[str, np.ndarray]:
    """Left-to-right anatomical axes (unit, (N, 3)) of the femur, humerus, hand, pelvis and head."""
    out = {}
    for seg, (lat, med) in {
        "femur": ("lateral_femoral_epicondyle", "medial_femoral_epicondyle"),
        "humerus": ("lateral_humeral_epicondyle", "medial_humeral_epicondyle"),
        "hand": ("radial_styloid", "ulnar_styloid"),
    }.items():
        out[f"{seg}_r"] = _unit(L[:, names.index(f"{lat}_r")] - L[:, names.index(f"{med}_r")])
        out[f"{seg}_l"] = _unit(L[:, names.index(f"{med}_l")] - L[:, names.index(f"{lat}_l")])
    asis_r, asis_l = _pair(L, names, "ASIS")
    out["pelvis"] = _unit(asis_r - asis_l)
    tr_r, tr_l = _pair(L, names, "tragion")
    out["head"] = _unit(tr_r - tr_l)
    return out


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _reject(v: np.ndarray, axis: np.ndarray) -> np.ndarray:
    return v - np.sum(v * axis, axis=-1, keepdims=True) * axis

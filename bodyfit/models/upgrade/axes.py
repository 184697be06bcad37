"""The input's up axis.

SMPL-format files do not say which world axis is up: SMPL's own frame is Y-up, AMASS's archive is Z-up (its
root orientations carry the turn), other tools write either. Our model and OpenSim are Y-up, so a Z-up input
fitted as it is comes out lying down. :func:`orient` finds the up axis from the motion itself and turns the
sequence into a Y-up world before anything is fitted.

How (:func:`detect_up`), on SMPL's joints posed by forward kinematics over (a sample of) the good frames:

1. For each of the six signed axes, heights along it: the lowest of the foot joints (ankles, toes) in each
   frame, the floor at the 5th percentile of those over the sequence.
2. The body's extent along the axis (the head above the frame's lowest foot joint, median over frames),
   less the spread of the root's height above that foot (standard deviation): the up axis is the one along
   which the body is tallest and the root keeps a roughly constant height over the feet (gravity). Both are
   taken within each frame, so a walk's travel, however long, adds nothing to a horizontal axis; measured
   from the sequence's floor instead, half the distance walked would count as height.
3. The sign: the head is above the feet.
4. The evidence is weak when the best axis's score leads the next by less than :data:`WEAK_MARGIN_M`, or the
   feet touch the floor (within :data:`CONTACT_M`) in fewer than :data:`CONTACT_MIN` of the frames; in a
   tie, a file that says it comes from AMASS (``surface_model_type`` smplh / smplx) is taken as AMASS's
   Z-up. A sequence whose feet touch no floor in any axis convention (the root floating or falling) is
   flagged.

Ground contact as the source of the vertical follows the floor-plane estimation of motion clean-up tools
(for instance D. Rempe, T. Birdal, A. Hertzmann, J. Yang, S. Sridhar and L. J. Guibas, "HuMoR: 3D Human
Motion Model for Robust Pose Estimation", ICCV 2021, whose fits stand a ground plane under the feet); AMASS's
Z-up convention: N. Mahmood, N. Ghorbani, N. F. Troje, G. Pons-Moll and M. J. Black, "AMASS: Archive of
Motion Capture as Surface Shapes", ICCV 2019.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from bodyfit.io.smpl import SmplSequence
from bodyfit.models.upgrade.smpl_model import SmplModel, rodrigues

UP_AXES = ("+x", "-x", "+y", "-y", "+z", "-z")
"""The signed axes an input's up may be given as (``up="+z"``; a bare "z" is "+z"); "auto" detects it."""
SAMPLE_FRAMES = 400  # frames the detection poses (evenly spread): the floor and heights need no more
FOOT_JOINTS = (7, 8, 10, 11)  # SMPL's ankles and toes
HEAD, PELVIS = 15, 0
CONTACT_M = 0.10  # the lowest foot joint this close to the floor: a contact (ankles sit ~8 cm above it)
CONTACT_MIN = 0.2  # fewer contacts than this share of the frames: no plausible floor along that axis
WEAK_MARGIN_M = 0.3  # the best axis's score leads the next by less: weak evidence
AMASS_TYPES = ("smplh", "smplx")


@dataclass(frozen=True)
class UpAxis:
    """The input's up axis: ``axis`` one of :data:`UP_AXES`; ``rotation`` (3, 3) the turn of the input's
    world into the Y-up one (``y_up = rotation @ x``); ``given``: the user named it; ``scores`` the
    detection's score per signed axis (m; empty when given); ``contact`` the share of frames whose feet
    touch the floor along it; ``weak``: the evidence does not settle it; ``floor``: some axis convention
    has a plausible floor; ``reason``: what decided it, for the notes."""

    axis: str
    rotation: np.ndarray
    given: bool
    scores: dict[str, float]
    contact: float
    weak: bool
    floor: bool
    reason: str

    def notes(self) -> list[str]:
        """What the summary's notes say of the axes."""
        turned = "" if self.axis == "+y" else ", turned into a Y-up world"
        how = "given" if self.given else f"detected from the motion ({self.reason})"
        out = [
            f"the input's up axis: {self.axis} ({how}){turned}; coordinates, root and joints are in a Y-up "
            "world (OpenSim's), heading kept"
        ]
        if self.weak and not self.given:
            out.append(
                f"warning: the up axis is uncertain ({self.reason}); if the body looks tipped over, give the "
                "input's up axis (up=+z for AMASS files)"
            )
        if not self.floor:
            out.append(
                "warning: the feet never stand on a plausible floor in any axis convention (the root floats "
                "or falls, or trans is not in metres)"
            )
        return out

    def summary(self) -> dict[str, Any]:
        """JSON-ready fields for the summary."""
        return {"up_axis": self.axis, "up_given": self.given, "up_weak": self.weak, "floor_found": self.floor}


def up_axis_name(text: str | None) -> str | None:
    """The signed axis ``text`` names, as one of :data:`UP_AXES`; None for None, "" or "auto" (detect).

    Raises:
        ValueError: text naming no axis; the message names the allowed values.
    """
    if text is None or text.strip().lower() in ("", "auto"):
        return None
    key = text.strip().lower()
    key = key if key[:1] in ("+", "-") else f"+{key}"
    if key not in UP_AXES:
        raise ValueError(
            f"up must be auto or one of {', '.join(UP_AXES)} (a bare x, y or z is +); got {text!r}"
        )
    return key


def axis_vector(axis: str) -> np.ndarray:
    """(3,) unit vector of a signed axis name ("-z" -> (0, 0, -1))."""
    v = np.zeros(3)
    v["xyz".index(axis[1])] = 1.0 if axis[0] == "+" else -1.0
    return v


def turn_to_y_up(axis: str) -> np.ndarray:
    """(3, 3) the quarter (or half) turn that takes ``axis`` onto +Y, about a horizontal axis of the input's
    frame (so the heading's axis is kept: +Z up turns about X)."""
    u = axis_vector(axis)
    y = np.array([0.0, 1.0, 0.0])
    if u @ y > 0.5:
        return np.eye(3)
    if u @ y < -0.5:
        return np.diag([1.0, -1.0, -1.0])  # half a turn about X
    k = np.cross(u, y)
    return rodrigues(k * (np.pi / 2) / np.linalg.norm(k))


def posed_joints(smpl: SmplModel, poses: np.ndarray, betas: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """SMPL's joints (T, J, 3) posed by forward kinematics alone (no skin): poses (T, J, 3) axis-angle,
    betas (K,), trans (T, 3) metres."""
    b = np.zeros(smpl.n_betas)
    k = min(len(betas), smpl.n_betas)
    b[:k] = betas[:k]
    shaped = smpl.v_template + smpl.shapedirs @ b
    J = smpl.J_regressor @ shaped  # (J, 3)
    R = rodrigues(poses.reshape(len(poses), -1, 3))  # (T, J, 3, 3)
    G_R = np.empty_like(R)
    out = np.empty((len(poses), smpl.n_joints, 3))
    for j, parent in enumerate(smpl.parents):
        if parent < 0:
            G_R[:, j], out[:, j] = R[:, j], J[j] + trans
        else:
            G_R[:, j] = G_R[:, parent] @ R[:, j]
            out[:, j] = out[:, parent] + G_R[:, parent] @ (J[j] - J[parent])
    return out


def detect_up(joints: np.ndarray, surface_model_type: str = "smpl") -> UpAxis:
    """The up axis of joints (T, 24, 3) in SMPL's joint order (see the module docstring)."""
    scores: dict[str, float] = {}
    contacts: dict[str, float] = {}
    for axis in UP_AXES:
        h = joints @ axis_vector(axis)  # (T, J)
        lowest = h[:, FOOT_JOINTS].min(axis=1)
        floor = np.percentile(lowest, 5)
        contacts[axis] = float((lowest - floor < CONTACT_M).mean())
        extent = float(np.median(h[:, HEAD] - lowest))  # negative when the head is below the feet
        scores[axis] = extent - float(np.std(h[:, PELVIS] - lowest))
    ranked = sorted(scores, key=lambda a: -scores[a])
    best, second = ranked[0], ranked[1]
    margin = scores[best] - scores[second]
    weak = margin < WEAK_MARGIN_M or contacts[best] < CONTACT_MIN
    reason = (
        f"score {scores[best]:.2f} m: the body's height less its root's height spread, {margin:.2f} m ahead "
        f"of {second}; feet on the floor in {contacts[best]:.0%} of the frames"
    )
    if weak and surface_model_type in AMASS_TYPES and "+z" in ranked[:2] and best != "+z":
        best, reason = "+z", f"{reason}; the file says AMASS ({surface_model_type}), whose worlds are Z-up"
    floor_found = any(c >= CONTACT_MIN for c in contacts.values())
    return UpAxis(best, turn_to_y_up(best), False, scores, contacts[best], weak, floor_found, reason)


def given_up(axis: str) -> UpAxis:
    """The :class:`UpAxis` a user named (one of :data:`UP_AXES`)."""
    return UpAxis(axis, turn_to_y_up(axis), True, {}, float("nan"), False, True, "given")


def orient(sequence: SmplSequence, smpl: SmplModel, up: str | None = None) -> tuple[SmplSequence, UpAxis]:
    """The sequence in a Y-up world, and its :class:`UpAxis`: ``up`` as given (one of :data:`UP_AXES`), or
    detected (None) from the good frames posed by ``smpl`` with the sequence's betas."""
    axis_name = up_axis_name(up)
    if axis_name is not None:
        found = given_up(axis_name)
    else:
        good = np.flatnonzero(~sequence.bad_frames)
        pick = good[
            np.unique(np.linspace(0, len(good) - 1, min(SAMPLE_FRAMES, len(good))).round().astype(int))
        ]
        joints = posed_joints(smpl, sequence.poses[pick], sequence.betas, sequence.trans[pick])
        found = detect_up(joints, sequence.surface_model_type)
    return turned(sequence, smpl, found.rotation), found


def turned(sequence: SmplSequence, smpl: SmplModel, rotation: np.ndarray) -> SmplSequence:
    """The sequence with its world turned by ``rotation`` (3, 3): the root orientation turned, and ``trans``
    moved so that the body turns about the world's origin, not about its own root joint (SMPL rotates the
    root about the rest root joint J0: a body at ``trans`` turned by R is at ``R (trans + J0) - J0``)."""
    if np.allclose(rotation, np.eye(3)):
        return sequence
    b = np.zeros(smpl.n_betas)
    k = min(len(sequence.betas), smpl.n_betas)
    b[:k] = sequence.betas[:k]
    j0 = smpl.J_regressor[0] @ (smpl.v_template + smpl.shapedirs @ b)
    root = rodrigues(sequence.poses[:, 0])
    poses = sequence.poses.copy()
    poses[:, 0] = _axis_angle(rotation @ root)
    trans = (sequence.trans + j0) @ rotation.T - j0
    bad = sequence.bad_frames
    return replace(
        sequence, poses=np.where(bad[:, None, None], 0.0, poses), trans=np.where(bad[:, None], 0.0, trans)
    )


def _axis_angle(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 3) axis-angle, angles in [0, pi] (stable near 0 and pi)."""
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(cos)
    w = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = np.sin(angle)
    small = sin > 1e-6
    axis = np.where(small[..., None], w / np.where(small, 2.0 * sin, 1.0)[..., None], 0.0)
    near_pi = (~small) & (cos < 0)
    if near_pi.any():  # the axis from R + I's largest column: R = 2 k k^T - I at pi
        S = (R[near_pi] + np.eye(3)) / 2.0
        col = np.argmax(np.einsum("...ii->...i", S), axis=-1)
        k = S[np.arange(len(S)), :, col]
        axis[near_pi] = k / np.linalg.norm(k, axis=-1, keepdims=True)
    return axis * angle[..., None]

"""SMPL's 24-joint tree (names, parents) and SMPL-like joint locations taken from our anatomical joints.

SMPL: M. Loper, N. Mahmood, J. Romero, G. Pons-Moll and M. J. Black, "SMPL: A Skinned Multi-Person Linear
Model", ACM Transactions on Graphics 34(6) (SIGGRAPH Asia), 2015.
"""

from __future__ import annotations

import numpy as np

from bodyfit.models.body.model import BodyModel

SMPL_JOINTS = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
    "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
    "left_hand", "right_hand",
)  # fmt: skip
SMPL_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21)
# SMPL-like joint locations from our anatomical joints: a joint name, or a weighted mix.
JOINT_FROM: dict[str, tuple[tuple[str, float], ...]] = {
    "pelvis": (("pelvis", 1.0),),
    "left_hip": (("hip_l", 1.0),),
    "right_hip": (("hip_r", 1.0),),
    "spine1": (("lumbosacral", 1.0),),
    "left_knee": (("knee_l", 1.0),),
    "right_knee": (("knee_r", 1.0),),
    "spine2": (("thoracolumbar", 1.0),),
    "left_ankle": (("ankle_l", 1.0),),
    "right_ankle": (("ankle_r", 1.0),),
    "spine3": (("thoracolumbar", 0.5), ("cervicothoracic", 0.5)),
    "left_foot": (("mtp_l", 1.0),),
    "right_foot": (("mtp_r", 1.0),),
    "neck": (("cervicothoracic", 1.0),),
    "left_collar": (("cervicothoracic", 0.6), ("shoulder_l", 0.4)),
    "right_collar": (("cervicothoracic", 0.6), ("shoulder_r", 0.4)),
    "head": (("skull_base", 1.0),),
    "left_shoulder": (("shoulder_l", 1.0),),
    "right_shoulder": (("shoulder_r", 1.0),),
    "left_elbow": (("elbow_l", 1.0),),
    "right_elbow": (("elbow_r", 1.0),),
    "left_wrist": (("wrist_l", 1.0),),
    "right_wrist": (("wrist_r", 1.0),),
    "left_hand": (("wrist_l", 1.4), ("elbow_l", -0.4)),
    "right_hand": (("wrist_r", 1.4), ("elbow_r", -0.4)),
}


def smpl_joint_locations(model: BodyModel, joints: np.ndarray) -> np.ndarray:
    """Our anatomical joints (B, J_ours, 3) -> SMPL-like joint locations (B, 24, 3), same frame."""
    idx = {n: i for i, n in enumerate(model.joint_names)}
    return np.stack([sum(w * joints[:, idx[n]] for n, w in JOINT_FROM[name]) for name in SMPL_JOINTS], axis=1)

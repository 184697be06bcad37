"""Path (b): SMPL joint rotations without an SMPL model file.

The rotations drive a proxy skeleton in SMPL's conventions (its 24-joint tree, +Y up, facing +Z, T-pose
rest), whose rest joints are placed on our mean body in a T-pose at SMPL-like locations taken from our
anatomical joints. The proxy's motion is then retargeted onto our skeleton like any mocap skeleton
(:func:`bodyfit.models.fitting.retarget.retarget`: bone directions and orientations, every coordinate within
its limits, pelvis angles unwrapped). Betas cannot be used without SMPL's shape directions: the shape is our
population mean, and the result says so.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.bvh import BvhJoint, BvhMotion
from bodyfit.models.fitting.mocap_io import lab_rotation
from bodyfit.models.fitting.retarget import Segment, SegmentMap
from bodyfit.models.fitting.smpl_topology import SMPL_TO_BODY

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
END_SITES = {"head": (0.0, 0.12, 0.0), "left_foot": (0.0, 0.0, 0.05), "right_foot": (0.0, 0.0, 0.05)}


def _limbs(side: str, s: str) -> tuple[Segment, ...]:
    return (
        Segment(f"femur_{s}", f"{side}_hip", (f"{side}_hip", f"{side}_knee"), (f"femur_{s}", f"tibia_{s}")),
        Segment(
            f"tibia_{s}", f"{side}_knee", (f"{side}_knee", f"{side}_ankle"), (f"tibia_{s}", f"talus_{s}")
        ),
        Segment(
            f"calcn_{s}", f"{side}_ankle", (f"{side}_ankle", f"{side}_foot"), (f"talus_{s}", f"toes_{s}")
        ),
        Segment(f"toes_{s}", f"{side}_foot"),
        Segment(
            f"humerus_{s}",
            f"{side}_shoulder",
            (f"{side}_shoulder", f"{side}_elbow"),
            (f"humerus_{s}", f"ulna_{s}"),
        ),
        Segment(f"ulna_{s}", f"{side}_elbow", (f"{side}_elbow", f"{side}_wrist"), (f"ulna_{s}", f"hand_{s}")),
        Segment(f"hand_{s}", f"{side}_wrist"),
    )


SMPL_MAP = SegmentMap(
    root="pelvis",
    hips=("left_hip", "right_hip"),
    legs=(("left_hip", "left_knee", "left_ankle"), ("right_hip", "right_knee", "right_ankle")),
    segments=(
        Segment("torso", "spine1", ("spine1", "spine3"), ("torso", "thorax")),
        Segment("thorax", "spine3", ("spine3", "neck"), ("thorax", "head")),
        Segment("head", "head", ("neck", "head_end"), None),
        *_limbs("left", "l"),
        *_limbs("right", "r"),
    ),
)
"""Which proxy joints drive which of our bodies (see :class:`~bodyfit.models.fitting.retarget.SegmentMap`)."""


def smpl_joint_locations(model: BodyModel, joints: np.ndarray) -> np.ndarray:
    """Our anatomical joints (B, J_ours, 3) -> SMPL-like joint locations (B, 24, 3), same frame."""
    idx = {n: i for i, n in enumerate(model.joint_names)}
    return np.stack([sum(w * joints[:, idx[n]] for n, w in JOINT_FROM[name]) for name in SMPL_JOINTS], axis=1)


def proxy_rest_pose(model: BodyModel) -> np.ndarray:
    """(n_dof,) SMPL's rest pose on our skeleton: OpenSim's neutral pose (legs straight, feet flat) with the
    arms raised sideways to horizontal."""
    skel = model.skeleton
    q = np.zeros(skel.n_dof)
    for side in ("r", "l"):
        q[skel.dof_index(f"arm_add_{side}")] = -np.pi / 2
    return q


def proxy_rest_joints(model: BodyModel, shape: np.ndarray | None = None) -> np.ndarray:
    """(24, 3) the proxy's rest joints in SMPL's frame: our body (``shape``, default the mean) in SMPL's
    rest pose (:func:`proxy_rest_pose`)."""
    c = np.zeros((1, model.n_shape)) if shape is None else shape[None]
    with torch.no_grad():
        joints = model.forward(c, proxy_rest_pose(model)[None], dtype=torch.float64).joints.numpy()
    return smpl_joint_locations(model, joints)[0] @ SMPL_TO_BODY


def proxy_motion(poses: np.ndarray, trans: np.ndarray, rest: np.ndarray, fps: float) -> BvhMotion:
    """The proxy skeleton's motion as a BVH-like skeleton (metres, SMPL's axes: +Y up, facing +Z).

    Args:
        poses: (T, 24, 3) SMPL axis-angle; trans: (T, 3); rest: (24, 3) rest joints; fps: frame rate.
    """
    T = len(poses)
    euler = Rotation.from_rotvec(poses.reshape(-1, 3)).as_euler("ZXY", degrees=True).reshape(T, 24, 3)
    rotations = ("Zrotation", "Xrotation", "Yrotation")
    joints = []
    for j, (name, parent) in enumerate(zip(SMPL_JOINTS, SMPL_PARENTS, strict=True)):
        offset = rest[j] - (rest[parent] if parent >= 0 else 0.0)
        channels = (("Xposition", "Yposition", "Zposition") if parent < 0 else ()) + rotations
        end = END_SITES.get(name)
        joints.append(BvhJoint(name, parent, offset, channels, None if end is None else np.asarray(end)))
    values = np.concatenate([trans, euler.reshape(T, -1)], axis=1)
    return BvhMotion(tuple(joints), values, 1.0 / fps, 1.0, lab_rotation("y", "z"), "SMPL proxy")

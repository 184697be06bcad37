"""SMPL's rest pose for path (b)'s proxy, read off SMPL-topology bodies.

SMPL joint rotations are relative to SMPL's rest pose: legs a little apart, knees and ankles not quite
straight, arms out sideways with the palms down. anny's SOMA rig, which path (b)'s proxy is built from, has a
T-pose of its own, and the same rotations applied to it give another posture: on a walk the knees and ankles
read 10-17 degrees off. The CC BY bodies in SMPL's topology (the build's ``data/smpl_ccby``) carry SMPL's
rest-pose geometry, so the proxy is turned into it before it is written:

1. each SMPL joint's segment is the proxy's vertices skinned mostly to it; its rotation from the proxy's
   T-pose to an SMPL-topology body (carried onto our topology) is the least-squares rotation between the
   centred vertex sets (Kabsch; W. Kabsch, "A solution for the best rotation to relate two sets of vectors",
   Acta Crystallographica A32, 1976), averaged over the bodies;
2. on a limb (:data:`LIMBS`) only the swing is kept: a near-cylinder leaves the twist about its long axis
   (from the joint to its child) undetermined, and a body's shape (a fuller calf) would turn it at random;
3. the rotations are made symmetric (SMPL's rest pose is), segments that cannot be read turn with their
   parent (:data:`UNREAD`), and each becomes a rotation relative to its parent in world-aligned axes,
   SMPL's (and the SOMA rig's) convention.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from bodyfit.models.upgrade.smpl_joints import SMPL_JOINTS, SMPL_PARENTS

LIMBS = (
    "left_hip", "right_hip", "left_knee", "right_knee", "left_collar", "right_collar", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow",
)  # fmt: skip
"""Segments whose twist about their own axis a rigid alignment cannot read."""
UNREAD = ("left_foot", "right_foot", "left_hand", "right_hand")
"""Segments whose alignment is unreliable (the toes of a flat foot, the fingers as one block): they turn with
their parent, as does a segment with fewer than :data:`MIN_VERTICES` vertices of its own (spine1 and spine2
in the SOMA weights)."""
MIN_VERTICES = 30
MIRROR = np.diag([-1.0, 1.0, 1.0])  # SMPL's frame (+X to the body's left) mirrored left to right
MIN_WEIGHT = 0.6
"""A vertex belongs to the segment it is skinned to at least this much. SOMA skins only 11 vertices to each
collar at 0.8 and 59 at 0.6: read there, SMPL's rest pose raises the collars by 8 degrees and lowers the arms
by 11 against SOMA's T-pose, which a collar turning with the chest leaves out."""


def segment_alignment(
    proxy: np.ndarray,
    bodies: np.ndarray,
    weights: np.ndarray,
    joints: np.ndarray,
    usable: np.ndarray | None = None,
) -> np.ndarray:
    """World rotations (24, 3, 3) turning each SMPL segment of the proxy's T-posed body ``proxy`` (V, 3) into
    its pose in ``bodies`` (K, V, 3) (the same topology and frame), over the vertices skinned to it by at
    least :data:`MIN_WEIGHT` in ``weights`` (V, 24) and ``usable`` (K, V) (default all); swing only on
    :data:`LIMBS`, about the bone from the joint to its first child in the proxy's ``joints`` (24, 3);
    the parent's rotation for :data:`UNREAD` and segments with too few vertices."""
    K = len(bodies)
    use = np.ones((K, len(proxy)), bool) if usable is None else np.asarray(usable, bool)
    child = {p: j for j, p in reversed(list(enumerate(SMPL_PARENTS))) if p >= 0}
    out = np.repeat(np.eye(3)[None], len(SMPL_JOINTS), axis=0)
    for j, name in enumerate(SMPL_JOINTS):  # parents first
        out[j] = out[max(SMPL_PARENTS[j], 0)]  # an unread segment turns with its parent
        if name in UNREAD:
            continue
        turns = []
        for k in range(K):
            m = (weights[:, j] >= MIN_WEIGHT) & use[k]
            if m.sum() < MIN_VERTICES:
                break
            a, b = proxy[m] - proxy[m].mean(0), bodies[k][m] - bodies[k][m].mean(0)
            turns.append(Rotation.align_vectors(b, a)[0])
        if len(turns) < K:
            continue
        R = Rotation.concatenate(turns).mean()
        if name in LIMBS:
            axis = joints[child[j]] - joints[j]
            R = swing(R, axis / np.linalg.norm(axis))
        out[j] = R.as_matrix()
    return out


def swing(R: Rotation, axis: np.ndarray) -> Rotation:
    """The swing of R about unit ``axis`` (3,): the smallest rotation taking ``axis`` where R takes it."""
    turned = R.apply(axis)
    return Rotation.align_vectors(turned[None], axis[None])[0]


def rest_alignment(world: np.ndarray) -> np.ndarray:
    """World rotations (24, 3, 3) (:func:`segment_alignment`) -> the same, made symmetric, each relative to
    its parent in world-aligned axes (the root's in the world): what poses the proxy's T-pose into SMPL's
    rest pose."""
    names = list(SMPL_JOINTS)
    twin = [
        names.index(n.replace("left_", "right_")) if n.startswith("left_")
        else names.index(n.replace("right_", "left_")) if n.startswith("right_") else j
        for j, n in enumerate(names)
    ]  # fmt: skip
    mirrored = MIRROR @ world[twin] @ MIRROR
    R = np.stack([Rotation.from_matrix(np.stack(pair)).mean().as_matrix() for pair in zip(world, mirrored)])
    parent = np.array([p if p >= 0 else j for j, p in enumerate(SMPL_PARENTS)])
    local = np.einsum("jba,jbc->jac", R[parent], R)  # R_parent^T R_j
    local[0] = R[0]
    return local


def rest_rotations_deg(local: np.ndarray) -> dict[str, list[float]]:
    """The alignment's rotation vectors in degrees per SMPL joint (for the build's metrics)."""
    vectors = Rotation.from_matrix(local).as_rotvec(degrees=True)
    return {name: [round(float(x), 2) for x in v] for name, v in zip(SMPL_JOINTS, vectors, strict=True)}

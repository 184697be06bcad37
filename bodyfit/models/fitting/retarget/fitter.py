"""BVH motion onto our skeleton: named coordinates per frame, scaled to a body, angles continuous in time.

How (:func:`retarget`):

1. Calibration. The BVH rest pose (every channel zero) is matched by our skeleton on bone directions only
   (inverse kinematics from our zero pose, so twists stay neutral), giving ``q_ref``. Each of our bodies is
   then attached rigidly to its BVH segment: ``C_b = R_seg,rest^T R_b(q_ref)``.
2. Per frame, the pelvis coordinates come straight from the BVH root's orientation (``R = Rz Rx Ry``:
   tilt, list, rotation) and are unwrapped over time, so a subject turning past 180 degrees gives a
   continuous ``pelvis_rotation``. The other coordinates are fitted in the pelvis frame to the segments'
   directions (hip to knee, knee to ankle, ...) and, with a lower weight, to their orientations
   ``R_seg(t) C_b`` (which carry the twists), by batched L-BFGS through the bounded mapping, so every value is
   within its joint limits. All frames are solved at once, then again from (and pulled to) the running
   median of that answer, which keeps ambiguous joints on one branch from frame to frame.
3. Root translation: the BVH hip-joint midpoint scaled by our leg length over the BVH's, with our pelvis
   origin placed from it through the pelvis orientation.

The map from BVH joints to our bodies is a :class:`SegmentMap`; :data:`CMU_MAP` serves the CMU database's
31-joint skeleton (its BVH conversions).

Methods: L-BFGS (D. C. Liu and J. Nocedal, "On the limited memory BFGS method for large scale optimization",
Mathematical Programming 45, 1989) through the tanh-bounded coordinates of BLSM (eq. 6 of H. Wang, R. A.
Güler, I. Kokkinos, G. Papandreou and S. Zafeiriou, "BLSM: A Bone-Level Skinned Model of the Human Mesh",
European Conference on Computer Vision (ECCV), 2020); the running median is Tukey's median smoother (J. W.
Tukey, "Exploratory Data Analysis", Addison-Wesley, 1977).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bodyfit.io.bvh import BvhMotion
from bodyfit.io.mocap import MocapFormatError
from bodyfit.models.errors import ShapeError
from bodyfit.models.fitting.common.lbfgs import batched_lbfgs
from bodyfit.models.rotations import zxy_angles
from bodyfit.models.skeleton.model import PELVIS_ROTATIONS, Skeleton


@dataclass(frozen=True)
class Segment:
    """One of our bodies driven by the BVH.

    body: our body name; joint: the BVH joint whose rotation moves it (None: direction only);
    direction: (from, to) BVH joints (``<joint>_end`` for end sites) spanning it, with ``ours`` the
    (from, to) of our bodies whose origins span the same bone, or None; weight: of the direction term.
    """

    body: str
    joint: str | None
    direction: tuple[str, str] | None = None
    ours: tuple[str, str] | None = None
    weight: float = 1.0


@dataclass(frozen=True)
class SegmentMap:
    """root: the BVH root joint (pelvis orientation); hips: (left, right) BVH hip joints; legs: BVH
    (hip, knee, ankle) per side for the length scale; segments: what drives our other bodies."""

    root: str
    hips: tuple[str, str]
    legs: tuple[tuple[str, str, str], tuple[str, str, str]]
    segments: tuple[Segment, ...]


def _limbs(side: str, s: str) -> tuple[Segment, ...]:
    """CMU segments of one side; side is "Left" / "Right", s our suffix "l" / "r"."""
    h = side[0].lower()
    return (
        Segment(f"femur_{s}", f"{side}Hip", (f"{side}Hip", f"{side}Knee"), (f"femur_{s}", f"tibia_{s}")),
        Segment(f"tibia_{s}", f"{side}Knee", (f"{side}Knee", f"{side}Ankle"), (f"tibia_{s}", f"talus_{s}")),
        Segment(f"calcn_{s}", f"{side}Ankle", (f"{side}Ankle", f"{side}Toe"), (f"talus_{s}", f"toes_{s}")),
        Segment(f"toes_{s}", f"{side}Toe"),
        Segment(
            f"humerus_{s}",
            f"{side}Shoulder",
            (f"{side}Shoulder", f"{side}Elbow"),
            (f"humerus_{s}", f"ulna_{s}"),
        ),
        Segment(f"ulna_{s}", f"{side}Elbow", (f"{side}Elbow", f"{side}Wrist"), (f"ulna_{s}", f"hand_{s}")),
        Segment(f"hand_{s}", f"{h}hand"),
    )


CMU_MAP = SegmentMap(
    root="Hips",
    hips=("LeftHip", "RightHip"),
    legs=(("LeftHip", "LeftKnee", "LeftAnkle"), ("RightHip", "RightKnee", "RightAnkle")),
    segments=(
        Segment("torso", "Chest", ("lowerback", "Chest2"), ("torso", "thorax")),
        Segment("thorax", "Chest2", ("Chest2", "Neck"), ("thorax", "head")),
        Segment("head", "Head", ("Neck", "Head_end"), None),
        *_limbs("Left", "l"),
        *_limbs("Right", "r"),
    ),
)

U_MAX = 12.0  # |u| beyond which tanh(u) is 1 to 4e-11
ROTATION_WEIGHT = 0.3  # orientation term (squared Frobenius) against the direction terms
PRIOR = 1e-3  # pulls under-determined DOFs (scapulae, spine split) towards neutral, per rad^2
TEMPORAL_WINDOW = 9  # frames of the running median the second pass starts from and is pulled to
TEMPORAL_PULL = 0.02  # per rad^2: 0.1 rad off the median costs as much as 0.8 degrees of bone direction


@dataclass(frozen=True)
class Retargeted:
    """Our skeleton's motion.

    coordinates: (T, n_dof) radians, continuous in time: the pelvis angles are unwrapped (so
    ``pelvis_rotation`` may leave [-pi, pi] when the subject turns round); every other value is within
    its limits. :meth:`in_range` folds the pelvis back for :meth:`BodyModel.forward`. root: (T, 3) metres;
    rate: frames per second; residual_deg: (T,) RMS angle between our bone directions and the BVH's.
    """

    coordinates: np.ndarray
    root: np.ndarray
    rate: float
    residual_deg: np.ndarray
    scale: float

    def in_range(self, skeleton: Skeleton) -> np.ndarray:
        """(T, n_dof) coordinates with the pelvis angles wrapped into (-pi, pi]."""
        return wrap_pelvis(self.coordinates, skeleton)


def wrap_pelvis(q: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    """q (..., n_dof) with the pelvis rotations wrapped into (-pi, pi] (the same orientations)."""
    out = np.array(q, np.float64, copy=True)
    for name in PELVIS_ROTATIONS:
        k = skeleton.dof_index(name)
        out[..., k] = np.pi - np.mod(np.pi - out[..., k], 2 * np.pi)
    return out


def unwrap_pelvis(q: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    """q (T, n_dof) with the pelvis rotations unwrapped along time (no 2 pi jumps between frames)."""
    out = np.array(q, np.float64, copy=True)
    for name in PELVIS_ROTATIONS:
        k = skeleton.dof_index(name)
        out[:, k] = np.unwrap(out[:, k])
    return out


class _Chain:
    """Our skeleton's FK in the pelvis frame with the pelvis coordinates fixed at zero."""

    def __init__(self, skeleton: Skeleton, scales: np.ndarray, seg_map: SegmentMap, names: list[str]) -> None:
        self.skel = skeleton
        self.fk = skeleton.kinematics(torch.float64)
        self.scales = torch.as_tensor(scales, dtype=torch.float64)[None]
        pelvis = [skeleton.dof_index(n) for n in PELVIS_ROTATIONS]
        self.free = np.setdiff1d(np.arange(skeleton.n_dof), pelvis)
        body = skeleton.body_names.index
        segs = seg_map.segments
        self.rot_bodies = [body(s.body) for s in segs if s.joint is not None]
        self.rot_joints = [names.index(s.joint) for s in segs if s.joint is not None]
        dirs = [s for s in segs if s.direction is not None]
        self.dir_bvh = np.array([[names.index(s.direction[0]), names.index(s.direction[1])] for s in dirs])  # type: ignore[index]
        self.dir_ours = [s.ours for s in dirs]
        self.dir_weight = torch.as_tensor([s.weight for s in dirs], dtype=torch.float64)
        self.dir_body_index = [body(s.body) for s in dirs]

    def frames(self, q_free: torch.Tensor) -> torch.Tensor:
        q = q_free.new_zeros(len(q_free), self.skel.n_dof)
        q[:, self.free] = q_free
        return self.fk(q, None, self.scales.expand(len(q), -1, -1)).frames

    def directions(self, F: torch.Tensor, bvh_dirs: torch.Tensor) -> torch.Tensor:
        """(B, n_dir, 3) unit directions of ours; where a segment has no ``ours`` pair (the head), its body's
        rotation carries the calibrated BVH direction ``bvh_dirs`` (n_dir, 3) given in the body frame."""
        body = self.skel.body_names.index
        out = []
        for k, pair in enumerate(self.dir_ours):
            if pair is None:
                continue
            d = F[:, body(pair[1]), :3, 3] - F[:, body(pair[0]), :3, 3]
            out.append((k, d / d.norm(dim=-1, keepdim=True)))
        D = torch.zeros(F.shape[0], len(self.dir_ours), 3, dtype=F.dtype)
        for k, d in out:
            D[:, k] = d
        for k, pair in enumerate(self.dir_ours):
            if pair is None:
                D[:, k] = torch.einsum("bij,j->bi", F[:, self.dir_body_index[k], :3, :3], bvh_dirs[k])
        return D


def _solve(
    chain: _Chain,
    q0: torch.Tensor,
    dirs: torch.Tensor,
    rots: torch.Tensor | None,
    local_dirs: torch.Tensor,
    iterations: int,
    centre: torch.Tensor | None = None,
    pull: float = 0.0,
) -> torch.Tensor:
    """Fit the free coordinates (B, n_free) to target directions (B, n_dir, 3) and rotations
    (B, n_rot, 3, 3) (or None), all in the pelvis frame, pulled towards ``centre`` (B, n_free) with weight
    ``pull`` per rad^2 when given. Returns the coordinates (B, n_free)."""
    skel = chain.skel
    lo = torch.as_tensor(skel.ranges[chain.free, 0])
    hi = torch.as_tensor(skel.ranges[chain.free, 1])
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)

    def q_of(u: torch.Tensor) -> torch.Tensor:
        # Clamped: a coordinate pressed against its limit would otherwise drive u so far that tanh's slope
        # underflows into denormal numbers, which are two orders of magnitude slower on CPUs.
        return mid + half * torch.tanh(u.clamp(-U_MAX, U_MAX))

    def losses(u: torch.Tensor) -> torch.Tensor:
        q = q_of(u)
        F = chain.frames(q)
        D = chain.directions(F, local_dirs)
        loss = (chain.dir_weight * ((D - dirs) ** 2).sum(-1)).sum(-1)
        if rots is not None:
            R = F[:, chain.rot_bodies, :3, :3]
            loss = loss + ROTATION_WEIGHT * ((R - rots) ** 2).sum((-1, -2)).sum(-1)
        loss = loss + PRIOR * (q**2).sum(-1)
        if centre is not None:
            loss = loss + pull * ((q - centre) ** 2).sum(-1)
        return loss

    margin = 0.02 * half
    q_start = torch.minimum(torch.maximum(q0, lo + margin), hi - margin)
    u0 = torch.atanh((q_start - mid) / half)
    return q_of(batched_lbfgs(losses, u0, iterations, history=10).z)


def _running_median(x: np.ndarray, window: int) -> np.ndarray:
    """Centred running median over time of x (T, n), edges padded by reflection."""
    h = window // 2
    if len(x) <= 1 or h == 0:
        return x.copy()
    padded = np.pad(x, ((h, h), (0, 0)), mode="reflect" if len(x) > h else "edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, window, axis=0)  # (T, n, window)
    return np.median(windows, axis=-1)


def retarget(
    motion: BvhMotion,
    skeleton: Skeleton,
    scales: np.ndarray | None = None,
    seg_map: SegmentMap = CMU_MAP,
    iterations: int = 60,
) -> Retargeted:
    """Retarget a BVH motion onto our skeleton.

    Args:
        motion: a parsed BVH (see :func:`~bodyfit.io.bvh.read_bvh`; units and axes set there).
        skeleton: ours.
        scales: (n_seg, 3) our segment scales (the body the motion is for), default ones.
        seg_map: which BVH joints drive which of our bodies (:data:`CMU_MAP`).
        iterations: L-BFGS iterations of each of the two passes over all frames.
    Returns:
        :class:`Retargeted`.
    Raises:
        MocapFormatError: the BVH lacks a joint the map needs, or has no frames.
        ShapeError: scales of the wrong shape.
    """
    if motion.n_frames == 0:
        raise MocapFormatError(f"{motion.source} has no frames to retarget")
    n_seg = len(skeleton.segments)
    s = np.ones((n_seg, 3)) if scales is None else np.asarray(scales, np.float64)
    if s.shape != (n_seg, 3):
        raise ShapeError(f"scales must have shape ({n_seg}, 3); got {s.shape}")
    pos, rot, names = motion.world(end_sites=True)
    _check_joints(motion, seg_map, names)
    chain = _Chain(skeleton, s, seg_map, names)

    # Rest pose (every channel zero) in our axes.
    rest = BvhMotion(motion.joints, np.zeros((1, motion.values.shape[1])), motion.frame_time, motion.units,
                     motion.rotation, motion.source)  # fmt: skip
    pos0, rot0, _ = rest.world(end_sites=True)
    M = rot0[0, 0]  # the file-to-ours rotation (every rest rotation equals it)
    a, b = chain.dir_bvh[:, 0], chain.dir_bvh[:, 1]
    # Directions in the root's frame (ours after calibration: the root's rest frame is M).
    d_rest = _unit(pos0[0, b] - pos0[0, a])  # our axes; the pelvis is upright and faces +X at rest
    q_ref, local, C = _calibrate(chain, d_rest, M)

    # Per frame, in the root's frame.
    R_root = rot[:, names.index(seg_map.root)]  # (T, 3, 3) ours; equals M at rest
    R_pelvis = R_root @ M.T  # our pelvis orientation (upright, facing +X at rest)
    to_local = np.swapaxes(R_pelvis, -1, -2)
    d_t = np.einsum("tij,tkj->tki", to_local, _unit(pos[:, b] - pos[:, a]))
    R_t = np.einsum("tij,tkjl,klm->tkim", to_local, rot[:, chain.rot_joints], C)
    q_free = _solve_frames(chain, q_ref, torch.as_tensor(d_t), torch.as_tensor(R_t), local, iterations)
    q = np.zeros((motion.n_frames, skeleton.n_dof))
    q[:, chain.free] = q_free
    pelvis = [skeleton.dof_index(n) for n in PELVIS_ROTATIONS]
    q[:, pelvis] = zxy_angles(R_pelvis)
    q = unwrap_pelvis(q, skeleton)
    residual = _residual_degrees(chain, q_free, local, d_t)

    # Root: our hip-joint midpoint on the BVH's, scaled by leg length.
    scale, hip_ours = _leg_scale(chain, pos0[0], names, seg_map)
    hips = 0.5 * (pos[:, names.index(seg_map.hips[0])] + pos[:, names.index(seg_map.hips[1])])
    root_t = scale * hips - np.einsum("tij,j->ti", R_pelvis, hip_ours)
    return Retargeted(q, root_t, motion.rate, residual, scale)


def _unit(v: np.ndarray) -> np.ndarray:
    """``v`` (..., 3) scaled to unit length along its last axis."""
    return v / np.linalg.norm(v, axis=-1, keepdims=True).clip(1e-12)


def _check_joints(motion: BvhMotion, seg_map: SegmentMap, names: list[str]) -> None:
    """Nothing; raises MocapFormatError when the BVH (joint ``names``) lacks a joint ``seg_map`` needs."""
    needed = {seg_map.root, *seg_map.hips, *(j for leg in seg_map.legs for j in leg)}
    for seg in seg_map.segments:
        needed.update([seg.joint] if seg.joint else [])
        needed.update(seg.direction or ())
    missing = sorted(needed - set(names))
    if missing:
        raise MocapFormatError(
            f"{motion.source} lacks joints the retarget map needs: {', '.join(missing)} "
            f"(joints: {', '.join(names)})"
        )


def _calibrate(
    chain: _Chain, d_rest: np.ndarray, M: np.ndarray
) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
    """Our pose matching the BVH rest pose and each driven body's attachment to its BVH segment.

    Args:
        d_rest: (n_dir, 3) unit BVH rest directions in our axes; M: (3, 3) the file-to-ours rotation.
    Returns:
        q_ref (1, n_free); the local directions (n_dir, 3) of the segments without an origin pair (in
        their body's frame at q_ref, zero for the others); C (n_rot, 3, 3) = M^T R_b(q_ref).
    """
    n_free = len(chain.free)
    # Directions without an origin pair (the head's) are ignored here (zero local vector), then carried by
    # their body from q_ref on.
    local = torch.zeros(len(d_rest), 3, dtype=torch.float64)
    zero = torch.zeros(1, n_free, dtype=torch.float64)
    q_ref = _solve(chain, zero, torch.as_tensor(d_rest[None]), None, local, 150)
    F_ref = chain.frames(q_ref)
    for k, pair in enumerate(chain.dir_ours):
        if pair is None:
            local[k] = F_ref[0, chain.dir_body_index[k], :3, :3].T @ torch.as_tensor(d_rest[k])
    R_ref = chain.frames(q_ref)[0, chain.rot_bodies, :3, :3].numpy()
    C = np.einsum("ji,bjk->bik", M, R_ref)  # (n_rot, 3, 3) M^T R_b(q_ref)
    return q_ref, local, C


def _solve_frames(
    chain: _Chain,
    q_ref: torch.Tensor,
    d_all: torch.Tensor,
    R_all: torch.Tensor,
    local: torch.Tensor,
    iterations: int,
) -> np.ndarray:
    """(T, n_free) free coordinates of every frame fitted to directions (T, n_dir, 3) and rotations
    (T, n_rot, 3, 3) in the pelvis frame, from q_ref (1, n_free); local: (n_dir, 3) as :func:`_calibrate`.

    Every frame from the calibrated pose; then again from a median over time of that answer and pulled
    to it, which keeps each frame on the same branch as its neighbours where the fit is ambiguous (an arm
    near gimbal lock) without lagging: the median is centred.
    """
    first = _solve(chain, q_ref.expand(len(d_all), -1), d_all, R_all, local, iterations).numpy()
    centre = torch.as_tensor(_running_median(first, TEMPORAL_WINDOW))
    return _solve(chain, centre, d_all, R_all, local, iterations, centre, TEMPORAL_PULL).numpy()


def _residual_degrees(chain: _Chain, q_free: np.ndarray, local: torch.Tensor, d_t: np.ndarray) -> np.ndarray:
    """(T,) RMS angle (degrees) between our directions at q_free (T, n_free) and the targets d_t
    (T, n_dir, 3)."""
    with torch.no_grad():
        F = chain.frames(torch.as_tensor(q_free))
        D = chain.directions(F, local).numpy()
    cos = np.clip((D * d_t).sum(-1), -1.0, 1.0)
    return np.degrees(np.sqrt((np.arccos(cos) ** 2).mean(-1)))


def _leg_scale(
    chain: _Chain, rest_pos: np.ndarray, names: list[str], seg_map: SegmentMap
) -> tuple[float, np.ndarray]:
    """Our leg length over the BVH's (rest joint positions rest_pos (n_joints, 3), joints ``names``) and
    our hip-joint midpoint (3,) in the pelvis frame at the zero pose."""
    body = chain.skel.body_names.index
    F_ours = chain.frames(torch.zeros(1, len(chain.free), dtype=torch.float64))[0].numpy()
    hip_ours = 0.5 * (F_ours[body("femur_l"), :3, 3] + F_ours[body("femur_r"), :3, 3])
    leg_ours = np.mean([
        np.linalg.norm(F_ours[body(f"femur_{x}"), :3, 3] - F_ours[body(f"tibia_{x}"), :3, 3])
        + np.linalg.norm(F_ours[body(f"tibia_{x}"), :3, 3] - F_ours[body(f"talus_{x}"), :3, 3])
        for x in "lr"
    ])  # fmt: skip
    leg_bvh = np.mean([
        np.linalg.norm(rest_pos[names.index(h)] - rest_pos[names.index(k)])
        + np.linalg.norm(rest_pos[names.index(k)] - rest_pos[names.index(an)])
        for h, k, an in seg_map.legs
    ])  # fmt: skip
    return float(leg_ours / leg_bvh), hip_ours

"""Place the skeleton inside bodies: coordinates, root and per-segment scales from landmark-derived targets.

Build-time step after section 4.1 of H. Wang, R. A. Güler, I. Kokkinos, G. Papandreou and S. Zafeiriou, "BLSM:
A Bone-Level Skinned Model of the Human Mesh", ECCV 2020, with joint centres instead of CAESAR's landmarks:
for each body, minimise over coordinates q, root translation and log segment scales

    sum_p w_p |x_p(q, s) - x_p*|^2 + w_axis sum_a (1 - cos(axis_a(q), axis_a*))
      + regularisers (scales near-isotropic, tied segments alike, small coordinates),

where x_p are body-fixed skeleton points (joint centres, and bone-surface points such as the top of the
skull matched to skin landmarks) and axis_a are body axes matched to landmark axes (e.g. the femur's
left-right axis to the epicondyle axis), which fix the long-axis rotations joint centres cannot see. The
minimisation is L-BFGS (D. C. Liu and J. Nocedal, "On the limited memory BFGS method for large scale
optimization", Mathematical Programming 45, 1989) with a strong Wolfe line search.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bodyfit.models.body import landmarks as lmk
from bodyfit.models.body.model import body_points
from bodyfit.models.skeleton.model import Skeleton

# Joint-centre targets: target name -> (body, point in the body frame before scaling, weight).
# The cervicothoracic joint is the start of the cervical arc, 0.24 m above the thorax origin.
JOINT_POINTS: dict[str, tuple[str, tuple[float, float, float], float]] = {
    "pelvis": ("pelvis", (0.0, 0.0, 0.0), 1.0),
    "cervicothoracic": ("thorax", (0.0, 0.24, 0.0), 1.0),
    **{
        f"{joint}_{s}": (f"{body}_{s}", (0.0, 0.0, 0.0), 1.0)
        for s in ("r", "l")
        for joint, body in (
            ("hip", "femur"),
            ("knee", "tibia"),
            ("ankle", "talus"),
            ("mtp", "toes"),
            ("shoulder", "humerus"),
            ("elbow", "ulna"),
            ("wrist", "hand"),
        )
    },
}

# Skin landmarks matched by the outermost bone point of a body along a direction (body frame at q=0).
BONE_TIPS: dict[str, tuple[str, tuple[float, float, float], float]] = {
    "vertex": ("head", (0.0, 1.0, 0.0), 0.5),
    **{
        f"{lm}_{s}": (f"{body}_{s}", direction, 0.5)
        for s in ("r", "l")
        for lm, body, direction in (
            ("heel", "calcn", (-1.0, -0.3, 0.0)),
            ("toe_tip", "toes", (1.0, 0.0, 0.0)),
            ("dactylion", "hand", (0.0, -1.0, 0.0)),
        )
    },
}

# Body z axes (left-to-right) matched to landmark axes.
AXES = ("femur_r", "femur_l", "humerus_r", "humerus_l", "hand_r", "hand_l", "pelvis", "head")

RANGE_MARGIN = 0.25  # radians
SCALP_THICKNESS = 0.006  # metres of soft tissue over the top of the skull

# Segments without their own targets follow a neighbour.
TIED_SEGMENTS = (
    ("patella_r", "femur_r"),
    ("patella_l", "femur_l"),
    ("talus_r", "calcn_r"),
    ("talus_l", "calcn_l"),
    ("radius_r", "ulna_r"),
    ("radius_l", "ulna_l"),
    ("scapula_r", "thorax"),
    ("scapula_l", "thorax"),
    ("torso", "thorax"),
)


@dataclass(frozen=True)
class SkeletonFit:
    """Per-body skeleton placement. q: (N, n_dof); root: (N, 3); scales: (N, n_seg, 3);
    errors: target name -> (N,) distance in metres after the fit."""

    q: np.ndarray
    root: np.ndarray
    scales: np.ndarray
    errors: dict[str, np.ndarray]


def bone_tip_points(skeleton: Skeleton) -> dict[str, tuple[str, np.ndarray, float]]:
    """Body-frame points of :data:`BONE_TIPS`: the outermost bone vertex along each direction."""
    bones = skeleton.bone_mesh()
    names = skeleton.body_names
    out = {}
    for lm, (body, direction, weight) in BONE_TIPS.items():
        v = bones.vertices[bones.vertex_body == names.index(body)]
        out[lm] = (body, v[np.argmax(v @ np.asarray(direction))], weight)
    return out


def place_skeletons(skeleton: Skeleton, L: np.ndarray, iterations: int) -> SkeletonFit:
    """Fit the skeleton inside bodies from their landmark positions.

    Args:
        L: (N, n_landmark, 3) landmark positions in :func:`landmarks.landmark_names` order.
    """
    names = lmk.landmark_names()
    points = lmk.joint_targets(L, names)
    points.update({k: L[:, names.index(k)] for k in BONE_TIPS})
    points["vertex"] = points["vertex"] - np.array([0.0, SCALP_THICKNESS, 0.0])
    return fit_skeleton(skeleton, points, lmk.axis_targets(L, names), iterations=iterations)


def fit_skeleton(
    skeleton: Skeleton,
    points: dict[str, np.ndarray],
    axes: dict[str, np.ndarray],
    iterations: int = 300,
    chunk: int = 512,
) -> SkeletonFit:
    """Fit coordinates, root and segment scales of N bodies to target points and axes.

    Args:
        points: target name -> (N, 3); names from :data:`JOINT_POINTS` and :data:`BONE_TIPS`.
        axes: body name -> (N, 3) unit left-to-right axis, names from :data:`AXES`.
    """
    tips = bone_tip_points(skeleton)
    specs = {**{k: (b, np.asarray(p), w) for k, (b, p, w) in JOINT_POINTS.items()}, **tips}
    names = [k for k in specs if k in points]
    n = len(next(iter(points.values())))
    parts = [
        _fit_chunk(
            skeleton,
            specs,
            names,
            {k: points[k][i : i + chunk] for k in names},
            {k: axes[k][i : i + chunk] for k in AXES},
            iterations,
        )
        for i in range(0, n, chunk)
    ]
    errors = {k: np.concatenate([p.errors[k] for p in parts]) for k in names}
    return SkeletonFit(
        np.concatenate([p.q for p in parts]),
        np.concatenate([p.root for p in parts]),
        np.concatenate([p.scales for p in parts]),
        errors,
    )


def _fit_chunk(
    skeleton: Skeleton,
    specs: dict[str, tuple[str, np.ndarray, float]],
    names: list[str],
    points: dict[str, np.ndarray],
    axes: dict[str, np.ndarray],
    iterations: int,
) -> SkeletonFit:
    dt = torch.float64
    fk = skeleton.kinematics(dt)
    bodies = skeleton.body_names
    seg_of_body = np.asarray(skeleton.spec.body_segment_index)
    segs = skeleton.segments
    body_idx = torch.tensor([bodies.index(specs[k][0]) for k in names])
    seg_idx = torch.tensor(seg_of_body[body_idx.numpy()])
    local = torch.tensor(np.stack([specs[k][1] for k in names]), dtype=dt)
    w = torch.tensor([specs[k][2] for k in names], dtype=dt)
    target = torch.tensor(np.stack([points[k] for k in names], axis=1), dtype=dt)  # (N, P, 3)
    axis_body = torch.tensor([bodies.index(a) for a in AXES])
    axis_target = torch.tensor(np.stack([axes[a] for a in AXES], axis=1), dtype=dt)
    tie_a = torch.tensor([segs.index(a) for a, _ in TIED_SEGMENTS])
    tie_b = torch.tensor([segs.index(b) for _, b in TIED_SEGMENTS])
    # A rest pose may sit slightly outside the user-facing ranges (anny's knees are a little
    # hyperextended): the fit allows a margin; the ranges bind what users ask for, not the data.
    lo = torch.tensor(skeleton.ranges[:, 0], dtype=dt) - RANGE_MARGIN
    hi = torch.tensor(skeleton.ranges[:, 1], dtype=dt) + RANGE_MARGIN

    # Scales stay near-isotropic; the skull strictly so (its outline is matched only at the top).
    iso = torch.full((len(segs), 1), 1e-4, dtype=dt)
    iso[segs.index("head")] = 1e-1
    N = target.shape[0]
    q = torch.zeros(N, skeleton.n_dof, dtype=dt, requires_grad=True)
    root = target[:, names.index("pelvis")].clone().requires_grad_(True)
    log_s = torch.zeros(N, len(segs), 3, dtype=dt, requires_grad=True)

    def loss_fn() -> tuple[torch.Tensor, torch.Tensor]:
        s = torch.exp(log_s)
        frames = fk(q, root, s).frames
        x = body_points(frames, s, body_idx, seg_idx, local)
        dist2 = ((x - target) ** 2).sum(-1)  # (N, P)
        z = frames[:, axis_body, :3, 2]
        loss = (dist2 * w).sum() + 1e-3 * (1 - (z * axis_target).sum(-1)).sum()
        loss = loss + (iso * (log_s - log_s.mean(-1, keepdim=True)) ** 2).sum()
        loss = loss + 1e-3 * ((log_s[:, tie_a] - log_s[:, tie_b]) ** 2).sum()
        loss = loss + 1e-6 * (q**2).sum() + 1e-2 * (torch.relu(q - hi) ** 2 + torch.relu(lo - q) ** 2).sum()
        return loss, dist2

    opt = torch.optim.LBFGS(
        [q, root, log_s],
        lr=1.0,
        max_iter=iterations,
        history_size=50,
        line_search_fn="strong_wolfe",
        tolerance_grad=1e-12,
        tolerance_change=1e-15,
    )

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss, _ = loss_fn()
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        _, dist2 = loss_fn()
    err = dist2.sqrt().numpy()
    return SkeletonFit(
        q.detach().numpy(),
        root.detach().numpy(),
        torch.exp(log_s).detach().numpy(),
        {k: err[:, i] for i, k in enumerate(names)},
    )

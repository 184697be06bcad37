"""Bone geometry fitted inside the skin: one affine map per bone body, applied to its mesh in the body frame.

The skeleton's bodies are placed inside every body from joint centres and landmarks (:mod:`skeleton_fit`), but
the bone meshes come from one OpenSim subject (Rajagopal2015): a skull, hand or foot of another shape pokes
through a skin that its joints fit well. As SKEL scales each bone mesh and orients it with a per-bone,
shape-dependent rotation that aligns it with the limb's skin, apart from the joint transforms (M. Keller,
K. Werling, S. Shin, S. Delp, S. Pujades, C. K. Liu and M. J. Black, "From Skin to Skeleton: Towards
Biomechanically Accurate 3D Digital Humans", ACM Transactions on Graphics 42(6) (SIGGRAPH Asia), 2023,
section 5.2, eq. 8-9), each listed body's mesh gets an affine map
v -> A v + t in its body frame, before the segment scaling, fitted once at build time on the population in
the bind pose: minimise over A, t

    mean_p relu((x_p - y_p) . n_p + margin)^2 + lambda |A - I|^2 + mu |t|^2,

where x_p are the body's mapped, scaled and placed bone vertices and (y_p, n_p) the nearest skin vertex and
its outward normal (found again each round). Joint centres and frames are not changed: only the drawn bone
surface moves. Minimised by L-BFGS (D. C. Liu and J. Nocedal, "On the limited memory BFGS method for large
scale optimization", Mathematical Programming 45, 1989).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from bodyfit.models.skeleton.bones import BoneMesh

# Bodies whose meshes are fitted: those whose bone shape, not their joints, decides whether they stay inside.
FITTED_BODIES = (
    "head", "hand_r", "hand_l", "toes_r", "toes_l", "calcn_r", "calcn_l", "radius_r", "radius_l",
    "ulna_r", "ulna_l", "thorax", "pelvis",
)  # fmt: skip
MARGIN = 0.002  # metres of skin kept at least over every bone vertex
IDENTITY_WEIGHT = 1e-5  # lambda: against |A - I|^2 (the penalty's mean is in m^2: about 1e-5 per 3 mm)
SHIFT_WEIGHT = 1e-3  # mu: against |t|^2 in m^2
ROUNDS = 4
STRIDE = 3  # every 3rd bone vertex takes part


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (N, V, 3) of meshes (N, V, 3) with triangles (F, 3), pointing away
    from each mesh's centroid on the whole."""
    tri = vertices[:, faces]  # (N, F, 3, 3)
    n = np.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0])
    out = np.zeros_like(vertices)
    by_vertex = out.transpose(1, 0, 2)  # (V, N, 3) view: each triangle's normal added to its corners
    for k in range(3):
        np.add.at(by_vertex, faces[:, k], n.transpose(1, 0, 2))
    out /= np.maximum(np.linalg.norm(out, axis=-1, keepdims=True), 1e-12)
    centre = vertices.mean(axis=1, keepdims=True)
    outward = np.sign(np.sum((vertices - centre) * out, axis=(1, 2)))
    return out * outward[:, None, None]


def apply_bone_geometry(bones: BoneMesh, geometry: np.ndarray) -> np.ndarray:
    """Bone vertices (V, 3) in their body frames after each body's affine map; geometry (n_body, 3, 4)."""
    A, t = geometry[bones.vertex_body, :, :3], geometry[bones.vertex_body, :, 3]
    return np.einsum("vij,vj->vi", A, bones.vertices) + t


def fit_bone_geometry(
    bones: BoneMesh,
    body_names: list[str],
    skins: np.ndarray,
    faces: np.ndarray,
    frames: np.ndarray,
    scales: np.ndarray,
    iterations: int = 60,
) -> np.ndarray:
    """Fit the affine maps of :data:`FITTED_BODIES`.

    Args:
        bones: the bone mesh; body_names: the skeleton's bodies.
        skins: (N, V, 3) bodies in the bind pose; faces: (F, 3).
        frames: (N, n_body, 4, 4) their skeletons' body frames; scales: (N, n_body, 3) each body's segment
            scale (the scale of its segment, per body).
    Returns:
        (n_body, 3, 4) float64: [A | t] per body, identity for the bodies not fitted.
    """
    normals = vertex_normals(skins, faces)
    trees = [cKDTree(v) for v in skins]
    fitted = sorted(body_names.index(b) for b in FITTED_BODIES if b in body_names)
    pick = np.flatnonzero(np.isin(bones.vertex_body, fitted))[::STRIDE]
    owner = bones.vertex_body[pick]
    slot = torch.as_tensor(np.searchsorted(fitted, owner))
    local = torch.as_tensor(np.asarray(bones.vertices[pick], np.float64))
    R = torch.as_tensor(frames[:, owner, :3, :3])  # (N, P, 3, 3)
    o = torch.as_tensor(frames[:, owner][..., :3, 3])
    s = torch.as_tensor(scales[:, owner])  # (N, P, 3)
    A = torch.eye(3, dtype=torch.float64).repeat(len(fitted), 1, 1).requires_grad_(True)
    t = torch.zeros(len(fitted), 3, dtype=torch.float64, requires_grad=True)

    def placed() -> torch.Tensor:
        v = torch.einsum("pij,pj->pi", A[slot], local) + t[slot]
        return torch.einsum("npij,npj->npi", R, s * v) + o

    for _ in range(ROUNDS):
        with torch.no_grad():
            x = placed().numpy()
        idx = np.stack([tree.query(p)[1] for tree, p in zip(trees, x)])
        rows = np.arange(len(x))[:, None]
        y, n = torch.as_tensor(skins[rows, idx]), torch.as_tensor(normals[rows, idx])
        opt = torch.optim.LBFGS([A, t], lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe")

        def closure(y: torch.Tensor = y, n: torch.Tensor = n) -> torch.Tensor:
            A.grad, t.grad = None, None
            depth = ((placed() - y) * n).sum(-1) + MARGIN
            eye = torch.eye(3, dtype=torch.float64)
            loss = (torch.relu(depth) ** 2).mean() + IDENTITY_WEIGHT * ((A - eye) ** 2).sum()
            loss = loss + SHIFT_WEIGHT * (t**2).sum()
            loss.backward()
            return loss

        opt.step(closure)
    out = np.tile(np.eye(3, 4), (len(body_names), 1, 1))
    out[fitted, :, :3] = A.detach().numpy()
    out[fitted, :, 3] = t.detach().numpy()
    return out

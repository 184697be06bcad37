"""Skinning math: pure, batched torch functions (BLSM eq. 12; SKEL eq. 5)."""

from __future__ import annotations

import torch


def rigid_inverse(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid 4x4 transforms. T: (..., 4, 4) -> (..., 4, 4)."""
    R_t = T[..., :3, :3].transpose(-1, -2)
    t = -(R_t @ T[..., :3, 3:])
    top = torch.cat([R_t, t], dim=-1)
    return torch.cat([top, T[..., 3:, :]], dim=-2)


def skinning_transforms(frames: torch.Tensor, bind_frames: torch.Tensor) -> torch.Tensor:
    """Per-body transforms from the bind pose to the pose: ``frames @ inv(bind_frames)``.

    Args:
        frames, bind_frames: (B, n_body, 4, 4) rigid body frames in the world.
    Returns:
        (B, n_body, 3, 4) affine rows (the constant last row dropped).
    """
    return (frames @ rigid_inverse(bind_frames))[..., :3, :]


def linear_blend(vertices: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """Linear blend skinning.

    Args:
        vertices: (B, V, 3) bind-pose vertices.
        weights: (V, n_body) skinning weights, rows summing to 1.
        transforms: (B, n_body, 3, 4) from :func:`skinning_transforms`.
    Returns:
        (B, V, 3) posed vertices.
    """
    return linear_blend_coordinate_major(vertices.permute(2, 0, 1), weights.T, transforms)


def linear_blend_coordinate_major(
    rest: torch.Tensor, weights_t: torch.Tensor, transforms: torch.Tensor
) -> torch.Tensor:
    """Linear blend skinning in the fast layout: coordinates outermost, vertices innermost.

    Each column of the blended 3x4 matrices is one GEMM (3 B, n) @ (n, V) laid out (3, B, V), so applying
    them is three broadcast multiply-adds over contiguous arrays: no slicing, gathering or tiny batched
    matmuls, fast in torch and ONNX Runtime at any batch size.

    Args:
        rest: (3, B, V) bind-pose vertex coordinates x, y, z.
        weights_t: (n_body, V) skinning weights, transposed.
        transforms: (B, n_body, 3, 4) from :func:`skinning_transforms`.
    Returns:
        (B, V, 3) posed vertices.
    """
    B, n = transforms.shape[:2]
    V = weights_t.shape[1]
    flat = transforms.permute(3, 2, 0, 1).reshape(4, 3 * B, n)  # (column c, row r * batch b, body)
    # Translation column, then x, y, z columns times the vertex coordinates: one GEMM each.
    posed = (flat[3] @ weights_t).reshape(3, B, V)
    for c in range(3):
        posed = posed + (flat[c] @ weights_t).reshape(3, B, V) * rest[c]
    return posed.permute(1, 2, 0)


def normalised_weights(raw: torch.Tensor, mask: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """BLSM eq. 19: W = f(W') / sum_j f(W'), f(x) = sqrt(x^2 + eps), restricted to a support mask.

    Args:
        raw: (V, n_body) free parameters W'.
        mask: (V, n_body) 1 where a vertex may depend on a body, else 0.
    Returns:
        (V, n_body) non-negative weights whose rows sum to 1.
    """
    f = torch.sqrt(raw**2 + eps) * mask
    return f / f.sum(dim=-1, keepdim=True)

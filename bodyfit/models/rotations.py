"""Rotation helpers (pure functions, batch first).

All matrices rotate column vectors: ``v_parent = R @ v_child``.
"""

from __future__ import annotations

import numpy as np
import torch


def cm_matmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Matrix product in the component-major layout: (I, L, ...) @ (L, K, ...) -> (I, K, ...), the batch
    dimensions last (broadcast). Batches of 3 x 3 or 4 x 4 products become a few large elementwise
    operations instead of thousands of tiny GEMMs, which is faster in ONNX Runtime and torch alike."""
    return (a.unsqueeze(2) * b.unsqueeze(0)).sum(1)


def cm_matvec(a: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Matrix-vector product in the component-major layout: (I, L, ...) @ (L, ...) -> (I, ...)."""
    return (a * v.unsqueeze(0)).sum(1)


def axis_angle_matrix(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rotation by ``angle`` about unit ``axis``.

    Rodrigues' formula (O. Rodrigues, "Des lois géométriques qui régissent les déplacements d'un système
    solide dans l'espace", Journal de Mathématiques Pures et Appliquées 5, 1840).

    Args:
        axis: (..., 3) unit vectors; broadcast against ``angle``.
        angle: (...) radians.
    Returns:
        (..., 3, 3) rotation matrices.
    """
    x, y, z = axis.unbind(-1)
    c = torch.cos(angle)
    s = torch.sin(angle)
    C = 1.0 - c
    row0 = torch.stack([c + x * x * C, x * y * C - z * s, x * z * C + y * s], dim=-1)
    row1 = torch.stack([y * x * C + z * s, c + y * y * C, y * z * C - x * s], dim=-1)
    row2 = torch.stack([z * x * C - y * s, z * y * C + x * s, c + z * z * C], dim=-1)
    return torch.stack([row0, row1, row2], dim=-2)


def euler_xyz_body_fixed(angles: np.ndarray) -> np.ndarray:
    """OpenSim frame orientation: XYZ body-fixed Euler angles -> rotation matrix.

    Args:
        angles: (..., 3) radians ``(a, b, c)``.
    Returns:
        (..., 3, 3) ``Rx(a) @ Ry(b) @ Rz(c)`` in float64.
    """
    a = np.asarray(angles, dtype=np.float64)
    ca, cb, cc = np.cos(a[..., 0]), np.cos(a[..., 1]), np.cos(a[..., 2])
    sa, sb, sc = np.sin(a[..., 0]), np.sin(a[..., 1]), np.sin(a[..., 2])
    one, zero = np.ones_like(ca), np.zeros_like(ca)
    rx = np.stack([one, zero, zero, zero, ca, -sa, zero, sa, ca], -1).reshape(*ca.shape, 3, 3)
    ry = np.stack([cb, zero, sb, zero, one, zero, -sb, zero, cb], -1).reshape(*ca.shape, 3, 3)
    rz = np.stack([cc, -sc, zero, sc, cc, zero, zero, zero, one], -1).reshape(*ca.shape, 3, 3)
    return rx @ ry @ rz


def matrix_to_euler_xyz_body_fixed(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`euler_xyz_body_fixed` (away from gimbal lock, ``|b| < pi/2``).

    Args:
        R: (..., 3, 3) rotation matrices.
    Returns:
        (..., 3) angles ``(a, b, c)`` with ``R = Rx(a) Ry(b) Rz(c)``.
    """
    R = np.asarray(R, dtype=np.float64)
    b = np.arcsin(np.clip(R[..., 0, 2], -1.0, 1.0))
    a = np.arctan2(-R[..., 1, 2], R[..., 2, 2])
    c = np.arctan2(-R[..., 0, 1], R[..., 0, 0])
    return np.stack([a, b, c], axis=-1)


def rotation_angle_between(Ra: torch.Tensor, Rb: torch.Tensor) -> torch.Tensor:
    """Geodesic angle between rotations.

    Args:
        Ra, Rb: (..., 3, 3).
    Returns:
        (...) radians in [0, pi].
    """
    rel = Ra.transpose(-1, -2) @ Rb
    # Robust for tiny angles: use the skew part together with the trace.
    skew = torch.stack(
        [rel[..., 2, 1] - rel[..., 1, 2], rel[..., 0, 2] - rel[..., 2, 0], rel[..., 1, 0] - rel[..., 0, 1]],
        -1,
    )
    trace = rel[..., 0, 0] + rel[..., 1, 1] + rel[..., 2, 2]
    return torch.atan2(0.5 * torch.linalg.vector_norm(skew, dim=-1), 0.5 * (trace - 1.0))


def zxy_angles(R: np.ndarray) -> np.ndarray:
    """Angles ``(a, b, c)`` with ``R = Rz(a) Rx(b) Ry(c)`` (Rajagopal's pelvis: tilt, list, rotation).

    Args:
        R: (..., 3, 3).
    Returns:
        (..., 3) radians, b in [-pi/2, pi/2].
    """
    b = np.arcsin(np.clip(R[..., 2, 1], -1.0, 1.0))
    a = np.arctan2(-R[..., 0, 1], R[..., 1, 1])
    c = np.arctan2(-R[..., 2, 0], R[..., 2, 2])
    return np.stack([a, b, c], axis=-1)


def kabsch(source: np.ndarray, target: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted rigid alignment per row: R, t minimising sum_k w_k |R s_k + t - x_k|^2.

    W. Kabsch, "A solution for the best rotation to relate two sets of vectors", Acta Crystallographica A
    32(5), 1976, with the determinant correction that keeps R a proper rotation (S. Umeyama, "Least-squares
    estimation of transformation parameters between two point patterns", IEEE Transactions on Pattern
    Analysis and Machine Intelligence 13(4), 1991).

    Non-finite target points are skipped; rows with fewer than 3 weighted finite points give NaN.

    Args:
        source: (K, 3); target: (B, K, 3); weights: (K,) or (B, K), non-negative.
    Returns:
        R (B, 3, 3) proper rotations; t (B, 3).
    """
    finite = np.isfinite(target).all(-1)
    w = np.broadcast_to(weights, finite.shape) * finite
    x = np.where(finite[..., None], target, 0.0)
    valid = (w > 0).sum(axis=1) >= 3
    w = np.where(valid[:, None], w, 1.0)
    w = w / w.sum(axis=1, keepdims=True)
    mu_s = w @ source
    mu_t = np.einsum("bk,bkc->bc", w, x)
    H = np.einsum("bk,bki,bkj->bij", w, source[None] - mu_s[:, None], x - mu_t[:, None])
    U, _, Vt = np.linalg.svd(H)
    V, Ut = np.swapaxes(Vt, 1, 2), np.swapaxes(U, 1, 2)
    D = np.zeros_like(H)
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = np.sign(np.linalg.det(V @ Ut))
    R = V @ D @ Ut
    t = mu_t - np.einsum("bij,bj->bi", R, mu_s)
    R[~valid], t[~valid] = np.nan, np.nan
    return R, t

"""Skinning math: pure, batched torch functions.

Linear blend skinning as in eq. 12 of H. Wang, R. A. Güler, I. Kokkinos, G. Papandreou and S. Zafeiriou,
"BLSM: A Bone-Level Skinned Model of the Human Mesh", European Conference on Computer Vision (ECCV), 2020, and
eq. 5 of M. Keller, K. Werling, S. Shin, S. Delp, S. Pujades, C. K. Liu and M. J. Black, "From Skin to
Skeleton: Towards Biomechanically Accurate 3D Digital Humans", ACM Transactions on Graphics 42(6) (SIGGRAPH
Asia), 2023.
"""

from __future__ import annotations

import numpy as np
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


def blend_rows(transforms: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Skinning transforms, component-major (3, 4, n, B), as the left factors of :func:`blend_block`'s
    GEMMs: rotations (3 * B * 3, n) with rows ordered (row, batch, column) and translations (3 * B, n)."""
    n = transforms.shape[2]
    rotations = transforms[:, :3].permute(0, 3, 1, 2).reshape(-1, n)
    translations = transforms[:, 3].permute(0, 2, 1).reshape(-1, n)
    return rotations, translations


def blend_block(
    rest: torch.Tensor, weights_t: torch.Tensor, rotations: torch.Tensor, translations: torch.Tensor
) -> torch.Tensor:
    """Linear blend skinning of one block of vertices by the bodies that carry it.

    The blended 3x3 matrices and translations of every vertex come from two GEMMs, (3 * B * 3, n) @ (n, V)
    and (3 * B, n) @ (n, V), so that applying them is one broadcast product, one sum over a middle axis
    and one sum: few, large, contiguous operations in torch and ONNX Runtime alike.

    Args:
        rest: (B, 3, V) bind-pose vertices, coordinates before vertices.
        weights_t: (n, V) skinning weights of these vertices on n bodies, transposed.
        rotations, translations: those bodies' rows from :func:`blend_rows`.
    Returns:
        (B, V, 3) posed vertices.
    """
    return blend_linear(rest, weights_t, rotations, translations).permute(1, 2, 0)


def blend_linear(
    rest: torch.Tensor, weights_t: torch.Tensor, rotations: torch.Tensor, translations: torch.Tensor
) -> torch.Tensor:
    """:func:`blend_block` with the posed vertices coordinates first, (3, B, V): the layout the GEMMs give,
    before the one transpose to the output's."""
    B, _, V = rest.shape
    linear = (rotations @ weights_t).reshape(3, B, 3, V)
    shift = (translations @ weights_t).reshape(3, B, V)
    return (linear * rest).sum(2) + shift


def linear_blend(
    vertices: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor, chunk: int = 128
) -> torch.Tensor:
    """Linear blend skinning of whole meshes, ``chunk`` meshes at a time.

    Args:
        vertices: (B, V, 3) bind-pose vertices.
        weights: (V, n_body) skinning weights, rows summing to 1.
        transforms: (B, n_body, 3, 4) from :func:`skinning_transforms`.
    Returns:
        (B, V, 3) posed vertices.
    """
    rest = vertices.transpose(1, 2)
    parts = [
        blend_block(
            rest[i : i + chunk], weights.T, *blend_rows(transforms[i : i + chunk].permute(2, 3, 1, 0))
        )
        for i in range(0, len(vertices), chunk)
    ]
    return torch.cat(parts)


def blend_blocks(weights: np.ndarray, n_blocks: int, step: int = 64) -> list[tuple[int, int, np.ndarray]]:
    """Split the vertices into ``n_blocks`` contiguous ranges that each depend on few bodies.

    Skinning a block costs about (its vertices) x (the bodies with weight on any of them); the ranges
    (cut at multiples of ``step``) minimise the sum of that by dynamic programming. Neighbouring template
    vertices mostly belong to the same limb, so the blocks need about a third of the dense blend's work.

    Args:
        weights: (V, n_body) skinning weights.
    Returns:
        [(start, stop, bodies)] covering 0..V in order; bodies: indices of the bodies with weight in
        ``start:stop`` (at least one).
    """
    cuts = range_cuts(weights.shape[0], step)
    used = weights != 0
    prefix = range_counts(used, cuts)
    m = len(cuts)
    cost = np.full((m, m), np.inf)
    for i in range(m - 1):
        support = ((prefix[i + 1 :] - prefix[i]) > 0).sum(axis=1)
        cost[i, i + 1 :] = (cuts[i + 1 :] - cuts[i]) * np.maximum(support, 1)
    blocks = []
    for i, j in best_partition(cost, n_blocks):
        bodies = np.flatnonzero(used[cuts[i] : cuts[j]].any(axis=0))
        blocks.append((int(cuts[i]), int(cuts[j]), bodies if len(bodies) else np.zeros(1, np.int64)))
    return blocks


def range_cuts(n: int, step: int) -> np.ndarray:
    """Candidate block boundaries (m,): the multiples of ``step`` below ``n``, and ``n``."""
    return np.unique(np.r_[np.arange(0, n, step), n])


def range_counts(used: np.ndarray, cuts: np.ndarray) -> np.ndarray:
    """(m, n_col) prefix sums over the ranges between ``cuts`` of a boolean (V, n_col) table: row k counts
    the rows of ``used[:cuts[k]]`` set in each column, so that any range's support is a difference."""
    return np.concatenate(
        [
            np.zeros((1, used.shape[1]), np.int64),
            np.cumsum(np.add.reduceat(used.astype(np.int64), cuts[:-1], axis=0), axis=0),
        ]
    )


def best_partition(cost: np.ndarray, n_blocks: int) -> list[tuple[int, int]]:
    """The split of cut points 0..m-1 into at most ``n_blocks`` consecutive ranges (i, j) of least total
    ``cost[i, j]`` (m, m), by dynamic programming over the number of ranges; in order."""
    m = len(cost)
    n_blocks = max(1, min(n_blocks, m - 1))
    best = np.full((n_blocks + 1, m), np.inf)
    best[0, 0] = 0.0
    arg = np.zeros((n_blocks + 1, m), np.int64)
    for k in range(1, n_blocks + 1):
        total = best[k - 1][:, None] + cost  # (from, to)
        arg[k] = np.argmin(total, axis=0)
        best[k] = total[arg[k], np.arange(m)]
    ranges = []
    j = m - 1
    for k in range(n_blocks, 0, -1):
        i = int(arg[k, j])
        ranges.append((i, j))
        j = i
    return ranges[::-1]


def normalised_weights(raw: torch.Tensor, mask: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """BLSM eq. 19: W = f(W') / sum_j f(W'), f(x) = sqrt(x^2 + eps), restricted to a support mask.

    From Wang et al., "BLSM: A Bone-Level Skinned Model of the Human Mesh", ECCV 2020: the mapping keeps the
    weights non-negative and normalised while W' is optimised freely.

    Args:
        raw: (V, n_body) free parameters W'.
        mask: (V, n_body) 1 where a vertex may depend on a body, else 0.
    Returns:
        (V, n_body) non-negative weights whose rows sum to 1.
    """
    f = torch.sqrt(raw**2 + eps) * mask
    return f / f.sum(dim=-1, keepdim=True)

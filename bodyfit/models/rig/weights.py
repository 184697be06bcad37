"""One person's skinning weights, solved from example poses of them.

P. Fechteler, A. Hilsmann and P. Eisert, "Example-based Body Model Optimization and Skinning", Eurographics
2016 Short Papers, section 4: with the template, the joints and every example's pose fixed, the skinning
weights of a vertex enter only that vertex's posed positions, linearly under linear blend skinning:

    x_kv ~ sum_j w_vj G_kj [p_v; 1]      (G_kj = T_kj T_bind,j^-1, the body's skinning transform in example k)

The paper descends on the weights one candidate at a time; here each vertex's small problem is solved
exactly, as a non-negative least-squares problem (C. L. Lawson and R. J. Hanson, "Solving Least Squares
Problems", Prentice-Hall, 1974, chapter 23):

    min_{w >= 0}  sum_k c_kv |A_kv w - x_kv|^2 + unity (1^T w - 1)^2 + smoothness |w - wbar_v|^2

over the bodies near the vertex only (those weighting it or its mesh neighbours two rings away: a skin
vertex follows the bodies around it, and weights on far bodies would only fit noise). ``wbar_v`` is the mean
of the neighbours' current weights, the paper's Laplacian smoothness: where the poses cannot tell two bodies
apart (a vertex far from every joint that bent), the weights stay those of the neighbourhood. The weights are
renormalised to sum to one exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import torch
from scipy.optimize import nnls

from bodyfit.models.body.model import BodyDecoder
from bodyfit.models.skeleton.spec import SkeletonSpec


@dataclass(frozen=True, kw_only=True)
class WeightConfig:
    """smoothness: weight of |w - wbar|^2 in m^2 per unit weight (against the data term in m^2); unity: of
    (sum w - 1)^2; rings: how many mesh rings around a vertex lend it their bodies; floor: weights below it
    do not lend a body; jointed: the bodies jointed to those are candidates too."""

    smoothness: float = 4e-6
    unity: float = 1.0
    rings: int = 2
    floor: float = 0.01
    jointed: bool = False


def adjacency(faces: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """(V, V) 0/1 vertex adjacency of the mesh ``faces`` (F, 3), without the diagonal."""
    i = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2], faces[:, 1], faces[:, 2], faces[:, 0]])
    j = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0], faces[:, 0], faces[:, 1], faces[:, 2]])
    a = sp.csr_matrix((np.ones(len(i)), (i, j)), shape=(n_vertices, n_vertices))
    a.data[:] = 1.0
    return a


def body_adjacency(spec: SkeletonSpec) -> np.ndarray:
    """(n_body, n_body) bool: each body with itself, its parent and its children (the skeleton's joints)."""
    names = list(spec.body_names)
    out = np.eye(len(names), dtype=bool)
    for joint in spec.joints:
        if joint.parent in names and joint.child in names:
            a, b = names.index(joint.parent), names.index(joint.child)
            out[a, b] = out[b, a] = True
    return out


def candidate_bodies(
    weights: np.ndarray, neighbours: sp.csr_matrix, bodies: np.ndarray, rings: int, floor: float
) -> np.ndarray:
    """(V, n_body) bool: the bodies weighting a vertex, or any vertex up to ``rings`` mesh rings away, by
    ``floor`` or more, and the bodies jointed to those (``bodies`` from :func:`body_adjacency`): a link body
    between two that carry skin (a spine segment) can carry it too."""
    reach = (neighbours + sp.identity(neighbours.shape[0], format="csr")).astype(bool)
    covered = sp.csr_matrix(weights >= floor)
    for _ in range(rings):
        covered = (reach @ covered).astype(bool)
    return (np.asarray(covered.toarray(), np.float64) @ bodies.astype(np.float64)) > 0


def skinning_columns(
    decoder: BodyDecoder, shape: np.ndarray, poses: np.ndarray, roots: np.ndarray, bind: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Every body's transform of every rest vertex in every example: columns (K, V, 3, n_body) of the
    posed positions ``G_kj [p_v; 1]``, and the rest vertices p (V, 3), for one shape (n_shape,), poses
    (K, n_dof), roots (K, 3) and the bind coordinates (n_dof,) under ``decoder`` (its offsets, weights and
    joints). Linear blend skinning only: the posed skin is ``columns @ w_v``."""
    dtype = decoder.bind_rot_t.dtype
    K = len(poses)
    with torch.no_grad():
        c = torch.as_tensor(np.tile(shape, (K + 1, 1)), dtype=dtype)
        q = torch.as_tensor(np.concatenate([bind[None], poses]), dtype=dtype)
        r = torch.as_tensor(np.concatenate([np.zeros((1, 3)), roots]), dtype=dtype)
        vertices, _, frames, _ = decoder(c, q, r)
    F = frames.double().numpy()
    G = F[1:] @ np.linalg.inv(F[0])[None]  # (K, n_body, 4, 4)
    rest = vertices[0].double().numpy()
    moved = rest @ G[:, :, :3, :3].transpose(0, 1, 3, 2) + G[:, :, None, :3, 3]  # (K, n_body, V, 3)
    return moved.transpose(0, 2, 3, 1), rest


def solve_weights(
    columns: np.ndarray,
    targets: np.ndarray,
    confidence: np.ndarray,
    current: np.ndarray,
    candidates: np.ndarray,
    neighbours: sp.csr_matrix,
    config: WeightConfig | None = None,
) -> np.ndarray:
    """Skinning weights (V, n_body), each row non-negative and summing to one (module docstring).

    Args:
        columns: (K, V, 3, n_body) from :func:`skinning_columns`; targets: (K, V, 3) the examples' vertices,
            metres, in the posed frame; confidence: (K, V) per-vertex weights (0 = unseen); current:
            (V, n_body) the weights now (the smoothness term's neighbourhood mean); candidates: (V, n_body)
            bool from :func:`candidate_bodies`; neighbours: (V, V) adjacency.
    """
    cfg = config or WeightConfig()
    degree = np.maximum(np.asarray(neighbours.sum(axis=1)).ravel(), 1.0)
    wbar = (neighbours @ current) / degree[:, None]
    K, V = targets.shape[:2]
    root_c = np.sqrt(confidence)  # (K, V)
    out = np.array(current, np.float64, copy=True)
    s, u = np.sqrt(cfg.smoothness), np.sqrt(cfg.unity)
    for v in range(V):
        bodies = np.flatnonzero(candidates[v])
        if len(bodies) < 2:
            continue  # one body carries it whatever the data: nothing to solve
        A = (columns[:, v][..., bodies] * root_c[:, v, None, None]).reshape(3 * K, len(bodies))
        b = (targets[:, v] * root_c[:, v, None]).reshape(3 * K)
        M = np.vstack([A, np.full((1, len(bodies)), u), s * np.eye(len(bodies))])
        rhs = np.concatenate([b, [u], s * wbar[v, bodies]])
        w, _ = nnls(M, rhs)
        total = w.sum()
        if total > 0:
            out[v] = 0.0
            out[v, bodies] = w / total
    return out

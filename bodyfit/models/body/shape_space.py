"""Linear shape spaces learned from a population (build time): PCA, bone correctives, joint regressor."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass(frozen=True)
class PCA:
    """mean (D,); basis (K, D) rows = std_k * unit component; std (K,); explained (K,) variance ratios."""

    mean: np.ndarray
    basis: np.ndarray
    std: np.ndarray
    explained: np.ndarray

    def project(self, X: np.ndarray) -> np.ndarray:
        """(N, D) -> (N, K) coefficients in units of standard deviations."""
        return np.asarray((X - self.mean) @ self.basis.T / self.std**2)

    def reconstruct(self, c: np.ndarray) -> np.ndarray:
        """(N, k <= K) -> (N, D) using the first k components."""
        return np.asarray(self.mean + c @ self.basis[: c.shape[1]])


def fit_pca(X: np.ndarray, k: int, seed: int = 0) -> PCA:
    """PCA of X (N, D) keeping k components (randomised SVD for large D). Explained ratios are of the
    total variance.

    The randomised SVD (``torch.svd_lowrank``) is that of N. Halko, P. G. Martinsson and J. A. Tropp, "Finding
    Structure with Randomness: Probabilistic Algorithms for Constructing Approximate Matrix Decompositions",
    SIAM Review 53(2), 2011.
    """
    mean = X.mean(axis=0)
    Xc = torch.as_tensor(X - mean)
    k = min(k, X.shape[0] - 1, X.shape[1])
    total = float((Xc**2).sum())
    if X.shape[1] <= 512:
        _, S, Vt = torch.linalg.svd(Xc, full_matrices=False)
        V = Vt.T
    else:
        gen_state = torch.random.get_rng_state()
        torch.manual_seed(seed)
        _, S, V = torch.svd_lowrank(Xc, q=min(k + 16, min(X.shape)), niter=6)
        torch.random.set_rng_state(gen_state)
    S, V = S[:k].numpy(), V[:, :k].numpy().T
    # A deterministic sign: the largest-magnitude entry of each component is positive.
    sign = np.sign(V[np.arange(k), np.abs(V).argmax(axis=1)])
    V = V * sign[:, None]
    std = S / np.sqrt(max(X.shape[0] - 1, 1))
    return PCA(mean, V * std[:, None], std, S**2 / total)


def fit_correctives(Y: np.ndarray, coeffs: np.ndarray) -> np.ndarray:
    """Bone-corrective blendshapes (BLSM eq. 7, 15): least squares Y - mean(Y) ~ coeffs @ P.

    From Wang et al., "BLSM: A Bone-Level Skinned Model of the Human Mesh", ECCV 2020, with the meshes already
    unposed to the bind pose, so eq. 15's skinning drops out and the fit is linear.

    Args:
        Y: (N, D) bind-pose vertices, flattened; coeffs: (N, K) bone coefficients.
    Returns:
        (K, D) correctives.
    """
    C = coeffs - coeffs.mean(axis=0)
    P, *_ = np.linalg.lstsq(C, Y - Y.mean(axis=0), rcond=None)
    return np.asarray(P)


def fit_joint_regressor(
    vertices: np.ndarray, joints: np.ndarray, candidates: int = 200, sum_weight: float = 10.0
) -> np.ndarray:
    """Non-negative joint regressor: one NNLS problem per joint.

    As in section 5.1 of M. Keller, K. Werling, S. Shin, S. Delp, S. Pujades, C. K. Liu and M. J. Black, "From
    Skin to Skeleton: Towards Biomechanically Accurate 3D Digital Humans", ACM Transactions on Graphics 42(6),
    2023, following M. Keller, S. Zuffi, M. J. Black and S. Pujades, "OSSO: Obtaining Skeletal Shape from
    Outside", IEEE/CVF Conference on Computer Vision and Pattern Recognition (CVPR), 2022. Each problem is
    solved by the active-set method of C. L. Lawson and R. J. Hanson, "Solving Least Squares Problems",
    Prentice-Hall, 1974 (``scipy.optimize.nnls``).

    Each joint uses the ``candidates`` template vertices nearest to it on the mean body; a weighted row
    asks the weights to sum to 1, so the regressor commutes with translation.

    Args:
        vertices: (N, V, 3) meshes; joints: (N, J, 3) their joint centres.
    Returns:
        (J, V) non-negative weights.
    """
    from scipy.optimize import nnls

    mean_v, mean_j = vertices.mean(axis=0), joints.mean(axis=0)
    R = np.zeros((joints.shape[1], vertices.shape[1]))
    for j in range(joints.shape[1]):
        near = np.argsort(np.linalg.norm(mean_v - mean_j[j], axis=1))[:candidates]
        A = vertices[:, near].transpose(0, 2, 1).reshape(-1, len(near))  # (N*3, C)
        b = joints[:, j].reshape(-1)
        A = np.vstack([A, sum_weight * np.ones((1, len(near)))])
        b = np.concatenate([b, [sum_weight]])
        w, _ = nnls(A, b, maxiter=50 * len(near))
        R[j, near] = w
    return R


def vertex_errors(pred: np.ndarray, target: np.ndarray) -> tuple[float, float]:
    """Mean and max per-vertex distance in mm. pred, target: (N, V, 3) in metres."""
    d = np.linalg.norm(pred - target, axis=-1) * 1e3
    return float(d.mean()), float(d.max())

"""Non-rigid refinement: move a fitted body's vertices onto a scan, for detail beyond the shape space.

The role of the refinement step of BLiSS (S. Muralikrishnan, C.-H. P. Huang, D. Ceylan and N. J. Mitra,
"BLiSS: Bootstrapped Linear Shape Space", International Conference on 3D Vision (3DV), 2024, section 3.3): the
parametric fit is the starting registration, refined non-linearly to capture what the shape space misses.
BLiSS refines with Neural Jacobian Fields; here the refinement is a Laplacian-regularised per-vertex
deformation (O. Sorkine, D. Cohen-Or, Y. Lipman, M. Alexa, C. Rössl and H.-P. Seidel, "Laplacian Surface
Editing", Eurographics/ACM SIGGRAPH Symposium on Geometry Processing, 2004) fitted by iterated closest points
(P. J. Besl and N. D. McKay, "A Method for Registration of 3-D Shapes", IEEE Transactions on Pattern Analysis
and Machine Intelligence 14(2), 1992): per-vertex offsets D (V, 3) minimise

    sum_j a_j |M_j + D_j - t_j|^2 + smoothness |L D|^2 + stiffness |D|^2

where t_j is vertex j's target from closest points in both directions (vertex -> nearest scan point, and each
scan point -> its nearest vertex), a_j their robust (Geman-McClure) weights, and L the mesh Laplacian. Each
round re-finds the closest points and solves one sparse linear system. The pull towards t_j acts along the
vertex's normal only (``tangential`` = 0): detail beyond the shape space lies across the surface, while a
pull along it slides vertices to wherever the nearest points happen to be and breaks the correspondence
with the template (the registration moves away from the true one at the same distance to the scan). Where
the scan has no points (holes, the far side of a single view) the offsets fade smoothly to zero, leaving the
parametric surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import cg

from bodyfit.models.fitting.common.nearest import PointTree
from bodyfit.models.fitting.common.surface import NormalOperators, laplacian, vertex_normals


@dataclass(frozen=True)
class NonRigidConfig:
    """rounds: closest-point updates; smoothness, stiffness: weights of |L D|^2 and |D|^2 against a data
    weight of one per vertex; sigma: Geman-McClure scale (m); max_distance: pairs further apart are ignored
    (m)."""

    rounds: int = 3
    smoothness: float = 4.0
    stiffness: float = 0.01
    sigma: float = 0.01
    max_distance: float = 0.04
    tangential: float = 0.0


def geman_mcclure_weights(distance: np.ndarray, sigma: float) -> np.ndarray:
    """IRLS weights (sigma^2 / (sigma^2 + d^2))^2 of the Geman-McClure loss, same shape as ``distance``.

    The loss of S. Geman and D. E. McClure, "Statistical methods for tomographic image reconstruction",
    Bulletin of the International Statistical Institute 52(4), 1987, minimised by iteratively reweighted least
    squares (P. W. Holland and R. E. Welsch, "Robust regression using iteratively reweighted least-squares",
    Communications in Statistics - Theory and Methods 6(9), 1977).
    """
    s2 = sigma * sigma
    return (s2 / (s2 + distance * distance)) ** 2


def refine_nonrigid(
    vertices: np.ndarray,
    faces: np.ndarray,
    points: np.ndarray,
    config: NonRigidConfig | None = None,
    scan_tree: PointTree | None = None,
    seen: np.ndarray | None = None,
) -> np.ndarray:
    """The registration (V, 3): ``vertices`` (V, 3) moved onto ``points`` (N, 3), same units (metres for
    the default config). ``faces`` (F, 3) give the Laplacian; ``scan_tree``: a kd-tree of ``points``;
    ``seen``: (V,) bool, the vertices the scan can have points on (a single view's side facing its sensor;
    default all): only they are paired with scan points, the rest follow through the smoothness term."""
    cfg = config or NonRigidConfig()
    M = np.asarray(vertices, np.float64)
    P = np.asarray(points, np.float64)
    V = len(M)
    tree = scan_tree if scan_tree is not None else PointTree(P)
    L = laplacian(faces, V)
    regulariser = (cfg.smoothness * (L.T @ L) + cfg.stiffness * sp.identity(V)).tocsr()
    density = V / max(len(P), 1)  # scan -> vertex pairs count like one vertex's worth per vertex
    D = np.zeros_like(M)
    paired = np.arange(V) if seen is None else np.flatnonzero(seen)
    normal_ops = NormalOperators.of(faces, V) if cfg.tangential != 1.0 else None
    for _ in range(cfg.rounds):
        current = M + D
        d_m, near = tree.query(current)
        w_m = geman_mcclure_weights(d_m, cfg.sigma) * (d_m < cfg.max_distance)
        if seen is not None:
            w_m = w_m * seen
        d_s, owner = PointTree(current[paired]).query(P)
        owner = paired[owner]
        w_s = geman_mcclure_weights(d_s, cfg.sigma) * (d_s < cfg.max_distance) * density
        a = w_m + np.bincount(owner, w_s, minlength=V)
        b = w_m[:, None] * P[near]
        for k in range(3):
            b[:, k] += np.bincount(owner, w_s * P[:, k], minlength=V)
        rhs = b - a[:, None] * M
        if cfg.tangential != 1.0:
            n = vertex_normals(current, faces, normal_ops)
            along = (rhs * n).sum(1, keepdims=True) * n
            rhs = along + cfg.tangential * (rhs - along)
        D = solve_offsets(a, rhs, regulariser, D)
    return M + D


def solve_offsets(
    a: np.ndarray, rhs: np.ndarray, regulariser: sp.csr_matrix, start: np.ndarray | None = None
) -> np.ndarray:
    """Per-vertex offsets D (V, 3) minimising ``sum_j a_j |D_j - rhs_j / a_j|^2 + D^T R D``: the sparse system
    (diag(a) + R) D = rhs, one conjugate-gradient solve (Jacobi preconditioned) per axis (M. R. Hestenes and
    E. Stiefel, "Methods of Conjugate Gradients for Solving Linear Systems", Journal of Research of the
    National Bureau of Standards 49(6), 1952).

    Args:
        a: (V,) data weights (non-negative); rhs: (V, 3); regulariser: (V, V) R, positive definite (e.g.
            smoothness L^T L + stiffness I); start: (V, 3) initial guess (default zeros).
    """
    system = (sp.diags(a) + regulariser).tocsr()
    jacobi = sp.diags(1.0 / system.diagonal())
    x0 = np.zeros_like(rhs) if start is None else start
    return np.stack(
        [cg(system, rhs[:, k], x0=x0[:, k], M=jacobi, rtol=1e-5, maxiter=500)[0] for k in range(3)], 1
    )

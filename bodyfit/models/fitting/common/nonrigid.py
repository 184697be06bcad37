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
round re-finds the closest points and solves one sparse linear system.

The stiffness is lowered from coarse to fine over the rounds (:class:`NonRigidStage`), as in the optimal-step
non-rigid ICP of B. Amberg, S. Romdhani and T. Vetter, "Optimal Step Nonrigid ICP Algorithms for Surface
Registration", IEEE Conference on Computer Vision and Pattern Recognition (CVPR), 2007: the first rounds move
whole regions (a hand whose fingers the shape space cannot spread, a heel that sticks out) with a stiff
surface and a wide reach, the last ones fit detail with a supple one and a short reach.

A pull acts along the vertex's normal only where the pair is close: detail beyond the shape space lies
across the surface, while a pull along it slides vertices to wherever the nearest points happen to be and
breaks the correspondence with the template (the registration moves away from the true one at the same
distance to the scan); the offsets' part along the surface is dropped there every round. Where the scan
has points the registration leaves unexplained, beyond the scan's own sampling (the fitted body has a
finger or a thumb where the scan has none, and none where the scan has one), the pulls near them keep a
share along the surface that grows with the distance: only that can bring a misplaced part across, and a
part once moved keeps the move. A vertex far from a scan that is all explained lies over a hole, or a part
the scan did not see: it gets no pull, and there (and on the far side of a single view) the offsets fade
smoothly to zero, leaving the parametric surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import cg

from bodyfit.models.fitting.common.nearest import PointTree
from bodyfit.models.fitting.common.surface import NormalOperators, laplacian, vertex_normals


@dataclass(frozen=True)
class NonRigidStage:
    """One level of the coarse-to-fine schedule: ``rounds`` closest-point updates with the weight
    ``smoothness`` of |L D|^2 (against a data weight of one per vertex), pairs further apart than
    ``max_distance`` (m) ignored and the rest weighted by Geman-McClure with scale ``sigma`` (m)."""

    smoothness: float
    max_distance: float
    sigma: float
    rounds: int


COARSE_TO_FINE = (
    NonRigidStage(smoothness=20.0, max_distance=0.08, sigma=0.03, rounds=4),
    NonRigidStage(smoothness=4.0, max_distance=0.06, sigma=0.02, rounds=4),
    NonRigidStage(smoothness=1.0, max_distance=0.05, sigma=0.012, rounds=4),
    NonRigidStage(smoothness=1.0, max_distance=0.04, sigma=0.008, rounds=4),
)


@dataclass(frozen=True)
class NonRigidConfig:
    """stages: the coarse-to-fine schedule (:class:`NonRigidStage`); stiffness: weight of |D|^2;
    tangential: the share of a close pair's pull kept along the surface (0: across it only); slide_from,
    slide_full (m): pairs this far apart keep a growing share of their pull along the surface, all of it
    from ``slide_full`` on; both are raised to ``slide_spacing`` times the scan's median point spacing, so
    a sparse scan's gaps between points do not count as distance."""

    stages: tuple[NonRigidStage, ...] = COARSE_TO_FINE
    stiffness: float = 0.01
    tangential: float = 0.0
    slide_from: float = 0.008
    slide_full: float = 0.02
    slide_spacing: tuple[float, float] = (1.0, 2.5)


def geman_mcclure_weights(distance: np.ndarray, sigma: float) -> np.ndarray:
    """IRLS weights (sigma^2 / (sigma^2 + d^2))^2 of the Geman-McClure loss, same shape as ``distance``.

    The loss of S. Geman and D. E. McClure, "Statistical methods for tomographic image reconstruction",
    Bulletin of the International Statistical Institute 52(4), 1987, minimised by iteratively reweighted least
    squares (P. W. Holland and R. E. Welsch, "Robust regression using iteratively reweighted least-squares",
    Communications in Statistics - Theory and Methods 6(9), 1977).
    """
    s2 = sigma * sigma
    return (s2 / (s2 + distance * distance)) ** 2


def slide_share(distance: np.ndarray, tangential: float, start: float, full: float) -> np.ndarray:
    """(N,) the share of each pull kept along the surface for pairs ``distance`` (N,) apart (m):
    ``tangential`` up to ``start``, rising linearly to one at ``full``."""
    ramp = np.clip((distance - start) / max(full - start, 1e-12), 0.0, 1.0)
    return tangential + (1.0 - tangential) * ramp


def normal_pull(pull: np.ndarray, normals: np.ndarray, share: np.ndarray) -> np.ndarray:
    """(N, 3) pulls (N, 3) with their component across unit ``normals`` (N, 3) kept whole and the rest
    scaled by ``share`` (N,)."""
    along = (pull * normals).sum(1, keepdims=True) * normals
    return along + share[:, None] * (pull - along)


def vertex_radius(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V,) the mean length of the edges at each vertex of a mesh (V, 3), (F, 3): how far from a vertex its
    share of the surface reaches (zero for unused vertices)."""
    f = np.asarray(faces, np.int64)
    i = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    j = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    length = np.linalg.norm(vertices[i] - vertices[j], axis=1)
    total = np.bincount(i, length, len(vertices)) + np.bincount(j, length, len(vertices))
    count = np.bincount(i, minlength=len(vertices)) + np.bincount(j, minlength=len(vertices))
    return np.divide(total, count, out=np.zeros(len(vertices)), where=count > 0)


def surface_gap(offset: np.ndarray, normals: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """(N,) the distance from points to the surface around their nearest vertex, approximated by the disc of
    ``radius`` (N,) about the vertex in its tangent plane (unit ``normals`` (N, 3)), for points at ``offset``
    (N, 3) from it: on a coarse mesh a point midway between vertices is on the surface, not an edge's
    length away from it."""
    height = (offset * normals).sum(1)
    across = np.linalg.norm(offset - height[:, None] * normals, axis=1)
    return np.hypot(height, np.maximum(across - radius, 0.0))


def scan_spacing(tree: PointTree, points: np.ndarray, sample: int = 5000) -> float:
    """The median distance (m) from a scan point to its nearest other point, over up to ``sample`` points
    (N, 3) of the scan (``tree`` holds them all)."""
    if len(points) < 2:
        return 0.0
    subset = points[:: max(1, len(points) // sample)]
    return float(np.median(tree.query(subset, k=2)[0][:, 1]))


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
    spacing = scan_spacing(tree, P)
    start = max(cfg.slide_from, cfg.slide_spacing[0] * spacing)
    full = max(cfg.slide_full, cfg.slide_spacing[1] * spacing, start)
    L = laplacian(faces, V)
    LtL = (L.T @ L).tocsr()
    paired = np.arange(V) if seen is None else np.flatnonzero(seen)
    normal_ops = NormalOperators.of(faces, V)
    D = np.zeros_like(M)
    slid = np.full(V, cfg.tangential)
    radius = vertex_radius(M, faces)
    for stage in cfg.stages:
        regulariser = (stage.smoothness * LtL + cfg.stiffness * sp.identity(V)).tocsr()
        for _ in range(stage.rounds):
            a, pull, share, normals = closest_pulls(
                M + D, faces, P, tree, paired, stage, cfg, (start, full), normal_ops, radius
            )
            # this round's target offsets, across the surface only where the pairs have been close all
            # along: the offsets' part along it is dropped there, so it cannot build up over the rounds; a
            # part once moved across (a misplaced finger) keeps that move as its pairs close in
            slid = np.maximum(slid, share)
            D = solve_offsets(a, normal_pull(a[:, None] * D + pull, normals, slid), regulariser, D)
    return M + D


def near_unexplained(
    current: np.ndarray, points: np.ndarray, gap: np.ndarray, start: float, reach: float
) -> np.ndarray:
    """(V,) bool: the registration's vertices (V, 3) within ``reach`` (m) of a scan point (N, 3) it leaves
    unexplained (its ``gap`` (N,) to the registration's surface beyond ``start``)."""
    unexplained = points[gap > start]
    if not len(unexplained):
        return np.zeros(len(current), bool)
    return PointTree(unexplained).query(current, reach)[0] < np.inf


def closest_pulls(
    current: np.ndarray,
    faces: np.ndarray,
    points: np.ndarray,
    tree: PointTree,
    paired: np.ndarray,
    stage: NonRigidStage,
    cfg: NonRigidConfig,
    slide: tuple[float, float],
    normal_ops: NormalOperators,
    radius: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One round's data term at the registration ``current`` (V, 3), from closest points both ways: every
    vertex in ``paired`` (indices) to its nearest scan point, and every scan point (N, 3) (``tree`` holds
    them) to its nearest vertex in ``paired``, the latter scaled so both directions count alike (one
    vertex's worth per vertex). ``slide``: the distances (m) where pulls start and finish sliding
    (:func:`slide_share`); ``radius`` (V,): :func:`vertex_radius` of the template.

    Returns:
        each vertex's total weight a (V,), weighted pull (V, 3) (the sum over its pairs of weight times
        (scan point - vertex)), the weighted mean share (V,) of its pulls allowed along the surface, and
        its unit normal (V, 3).
    """
    V = len(current)
    normals = vertex_normals(current, faces, normal_ops)
    start, full = slide
    d_s, owner = PointTree(current[paired]).query(points)
    owner = paired[owner]
    gap = surface_gap(points - current[owner], normals[owner], radius[owner])
    # a vertex slides only where the scan has points the registration leaves unexplained within reach: a
    # misplaced part, not a hole (beside one every scan point is explained)
    misplaced = near_unexplained(current, points, gap, start, stage.max_distance)
    d_m, near = tree.query(current)
    w_m = np.zeros(V)
    w_m[paired] = geman_mcclure_weights(d_m[paired], stage.sigma) * (d_m[paired] < stage.max_distance)
    # a vertex far from a scan that is all explained lies over a hole or an unseen part: left to smoothness
    w_m *= misplaced | (d_m <= start)
    share_m = np.where(misplaced, slide_share(d_m, cfg.tangential, start, full), cfg.tangential)
    w_s = geman_mcclure_weights(d_s, stage.sigma) * (d_s < stage.max_distance) * (V / max(len(points), 1))
    a = w_m + np.bincount(owner, w_s, minlength=V)
    shared = w_m * share_m + np.bincount(
        owner, w_s * slide_share(gap, cfg.tangential, start, full), minlength=V
    )
    pull = w_m[:, None] * (points[near] - current)
    for k in range(3):
        pull[:, k] += np.bincount(owner, w_s * (points[:, k] - current[owner, k]), minlength=V)
    share = np.divide(shared, a, out=np.full(V, cfg.tangential), where=a > 0)
    return a, pull, share, normals


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

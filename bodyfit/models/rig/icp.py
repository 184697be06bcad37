"""Raw scans in a rig: closest points between the posed rig and each scan's points, both ways, as targets.

A raw scan's registration (its own fit, refined non-rigidly) lies on the scan's surface but slides along it
by a centimetre or more: the template's vertices sit where the nearest points happened to be. A rig built on
such registrations learns the sliding as offsets. So the rig built from raw scans is refined by iterated
closest points (P. J. Besl and N. D. McKay, "A Method for Registration of 3-D Shapes", IEEE Transactions on
Pattern Analysis and Machine Intelligence 14(2), 1992) over all scans at once: every round, the rig posed as
each scan is paired with that scan's points, every vertex with its nearest point and every point with its
nearest vertex, the pairs weighted by Geman-McClure (S. Geman and D. E. McClure, "Statistical methods for
tomographic image reconstruction", Bulletin of the International Statistical Institute 52(4), 1987), and each
vertex's target is moved along its normal only (point to plane: Y. Chen and G. Medioni, "Object Modelling by
Registration of Multiple Range Images", Image and Vision Computing 10(3), 1992). The rig's shared offsets,
weights and joints and every scan's pose are then solved against those targets (:mod:`.build`): the
correspondence along the surface comes from the rig, which all scans share, not from any one scan.

Before those rounds, the shared shape and every scan's pose are fitted to all scans' points at once
(:func:`fit_to_points`), on the robust two-way Chamfer distance (H. G. Barrow, J. M. Tenenbaum, R. C. Bolles
and H. C. Wolf, "Parametric correspondence and chamfer matching: Two new techniques for image matching",
IJCAI 1977), point to plane from the scans' side, the pairs found again at every evaluation: unlike the
rounds' targets, which hold each vertex where it is along the surface, this lets the shape and the poses
slide the body along the scans, away from where the registrations' own correspondence left it. The fit is
slow to converge (the pairs change under it): 25 iterations leave the template 10.0 mm from the person's, 200
leave 7.5 mm (its soft tissue included) on the benchmark's raw subject.

The rounds' targets hold the poses too: a limb a few degrees off stays so, and the offsets learn the error.
So after every round every scan's pose alone is fitted again on the Chamfer distance through the person's rig
as it stands (its offsets, weights and joints): the rig shared by all scans, not the generic body, then
decides where each scan's limbs lie. The offsets solved in each round are kept across the template's surface
only (:func:`normal_part`): where a vertex sits along the skin is the shape space's and the poses' to say.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from bodyfit.models.fitting.common.nearest import PointTree
from bodyfit.models.fitting.common.nonrigid import geman_mcclure_weights
from bodyfit.models.fitting.common.surface import vertex_normals
from bodyfit.models.fitting.registered.fitter import BodyFit, DataTerm, RegisteredFitter
from bodyfit.models.fitting.registered.stages import ShapeSet, Stage
from bodyfit.models.fitting.scan.losses import geman_mcclure


@dataclass(frozen=True, kw_only=True)
class ClosestConfig:
    """max_distance: pairs further apart (m) are ignored; sigma: the Geman-McClure scale (m); rounds: the
    alternation's rounds when raw scans are given (each re-pairs the points); tangential: the share of each
    pull kept along the surface (0: across it only); chamfer_iterations: L-BFGS iterations of the joint
    Chamfer fit before the rounds (0: none), chamfer_points: each scan's points in it (a seeded sample),
    chamfer_sigma_mm: its Geman-McClure scale, chamfer_tangential: the weight of its in-plane distances;
    shape_prior: the weight of |c|^2 in every fit of a build from raw scans (coefficients in population
    standard deviations, against mm^2), thirty times a registered mesh's: a surface pins the shape's
    coefficients far less than a correspondence does, and the identity coefficients otherwise run to
    several standard deviations to absorb what lies beyond the shape space (on the benchmark's raw subject,
    held-out error over the generic model's 0.65, 0.59, 0.56, 0.59 and 0.64 for 0.03, 0.1, 0.3, 1 and 3);
    repose_after: the rounds (from 0) after which every raw scan's pose alone is fitted again on the Chamfer
    distance, through the person's rig as it stands, for repose_iterations L-BFGS iterations;
    offset_tangential: the share of each round's offset step kept along the template's surface (0: along
    its normals only, see :func:`normal_part`)."""

    max_distance: float = 0.04
    sigma: float = 0.01
    rounds: int = 8
    tangential: float = 0.0
    chamfer_iterations: int = 200
    chamfer_points: int = 20000
    chamfer_sigma_mm: float = 10.0
    chamfer_tangential: float = 0.1
    shape_prior: float = 0.3
    repose_after: tuple[int, ...] = (0, 1, 2, 3, 4, 5, 6, 7)
    repose_iterations: int = 60
    offset_tangential: float = 0.0


def closest_targets(
    vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, config: ClosestConfig | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Targets (V, 3) for a posed mesh's vertices (V, 3) (triangles ``faces`` (F, 3)) on a scan's points
    (N, 3), in the same frame, metres, and their confidence (V,) in [0, 1] (0: no point near).

    Both directions count alike: the points' pulls are scaled by V / N, so a vertex paired with its share
    of points gets as much from them as from its own nearest point."""
    cfg = config or ClosestConfig()
    V, N = len(vertices), len(points)
    normals = vertex_normals(vertices, faces)
    d_m, near = PointTree(points).query(vertices, cfg.max_distance)
    seen = np.isfinite(d_m)
    w_m = np.where(seen, geman_mcclure_weights(np.where(seen, d_m, 0.0), cfg.sigma), 0.0)
    pull_m = np.zeros((V, 3))
    pull_m[seen] = points[near[seen]] - vertices[seen]
    d_s, owner = PointTree(vertices).query(points, cfg.max_distance)
    kept = np.isfinite(d_s)
    owner, pts = owner[kept], points[kept]
    w_s = geman_mcclure_weights(d_s[kept], cfg.sigma) * (V / max(N, 1))
    a = w_m + np.bincount(owner, w_s, minlength=V)
    pull = w_m[:, None] * pull_m
    for k in range(3):
        pull[:, k] += np.bincount(owner, w_s * (pts[:, k] - vertices[owner, k]), minlength=V)
    pull = np.divide(pull, a[:, None], out=np.zeros((V, 3)), where=a[:, None] > 0)
    across = np.einsum("vi,vi->v", normals, pull)[:, None] * normals
    return vertices + across + cfg.tangential * (pull - across), np.clip(a / 2.0, 0.0, 1.0)


def normal_part(step: np.ndarray, template: np.ndarray, faces: np.ndarray, tangential: float) -> np.ndarray:
    """An offset step (V, 3) metres with its part along the surface of ``template`` (V, 3) (triangles
    ``faces`` (F, 3)) scaled by ``tangential`` (0: across the surface only).

    Raw scans tell where the skin is, not which point of it a vertex is: the rounds' targets move each vertex
    across the surface only, and what the solved offsets carry along it comes from the Laplacian spreading
    those pulls over the neighbours, where the shape space and the poses already place a vertex on the
    person. Kept across the surface, the person's template is the shape space's body with a scalar
    displacement along its normals, the detail of a displaced surface (A. Lee, H. Moreton and H. Hoppe,
    "Displaced Subdivision Surfaces", SIGGRAPH 2000); on the benchmark's raw subject, held-out error over
    the generic model's 0.517 with the full step, 0.510 across only."""
    normals = vertex_normals(template, faces)
    across = np.einsum("vi,vi->v", normals, step)[:, None] * normals
    return across + tangential * (step - across)


def chamfer_term(
    points: Sequence[np.ndarray], faces: np.ndarray, config: ClosestConfig, dtype: torch.dtype
) -> DataTerm:
    """The robust two-way Chamfer loss (K,) in mm^2 of K posed meshes (K, V, 3) in mm against each scan's
    points (N_k, 3) metres (module docstring):

        mean_i rho(d_plane(p_i, v_j(i))) + 0.5 mean_v min(rho(|v - s(v)|), rho(reach))

    (rho(d) = d^2 s^2 / (d^2 + s^2), the Geman-McClure loss of ``chamfer_sigma_mm``)
    with j(i) the vertex nearest the point p_i, d_plane its distance across the vertex's normal plus
    ``chamfer_tangential`` of the in-plane part, s(v) the point nearest the vertex (both found again at every
    evaluation), and ``reach`` = ``max_distance``: a vertex over a hole in the scan pulls no further."""
    pts = [torch.as_tensor(p * 1000.0, dtype=dtype) for p in points]
    trees = [PointTree(p) for p in points]
    s2 = config.chamfer_sigma_mm**2
    cap = geman_mcclure(torch.tensor((config.max_distance * 1000.0) ** 2, dtype=dtype), s2)
    tangential = config.chamfer_tangential

    def term(verts_mm: torch.Tensor) -> torch.Tensor:
        v = verts_mm.detach().double().numpy() / 1000.0
        out = []
        for k, scan in enumerate(points):
            pairs = torch.as_tensor(PointTree(v[k]).query(scan)[1])
            nearest = torch.as_tensor(scan[trees[k].query(v[k])[1]] * 1000.0, dtype=dtype)
            normals = torch.as_tensor(vertex_normals(v[k], faces), dtype=dtype)[pairs]
            r = verts_mm[k][pairs] - pts[k]
            along = (r * normals).sum(-1)
            d2 = along**2 + tangential * ((r**2).sum(-1) - along**2)
            m2 = ((verts_mm[k] - nearest) ** 2).sum(-1)
            out.append(geman_mcclure(d2, s2).mean() + 0.5 * torch.minimum(geman_mcclure(m2, s2), cap).mean())
        return torch.stack(out)

    return term


def fit_to_points(
    fitter: RegisteredFitter,
    points: Sequence[np.ndarray],
    start: BodyFit,
    config: ClosestConfig,
    shape: ShapeSet = "all",
    iterations: int | None = None,
) -> BodyFit:
    """One shape and K poses fitted to K raw scans' points (N_k, 3) metres together (:func:`chamfer_term`),
    on every vertex of ``fitter``'s decoder, from ``start`` (its first shape); ``config.chamfer_points`` of
    each scan's points, a seeded sample; ``shape`` the coefficients freed (``"none"``: the poses alone),
    ``iterations`` L-BFGS iterations (None: ``config.chamfer_iterations``). The answer carries no reports
    (it is not a fit to meshes)."""
    rng = np.random.default_rng(0)
    sample = [p[rng.choice(len(p), min(config.chamfer_points, len(p)), replace=False)] for p in points]
    dtype = fitter.config.dtype
    z = fitter.start_state(start.coordinates, start.root, start.shape[:1])
    stage = Stage(
        name="chamfer",
        coordinates="all",
        shape=shape,
        vertices="all",
        iterations=config.chamfer_iterations if iterations is None else iterations,
    )
    fitter.optimise(stage, z, chamfer_term(sample, fitter.model.faces, config, dtype))
    c, q, r = fitter.parameters(z)
    with torch.no_grad():
        v, joints, _, _ = fitter.decoder(c.to(dtype), q.to(dtype), r.to(dtype))
    return BodyFit(c.numpy(), q.numpy(), r.numpy(), v.double().numpy(), joints.double().numpy())

"""The scan fit's losses: the robust two-way Chamfer term its L-BFGS minimises (:func:`chamfer_term`), its
Gauss-Newton metric (:func:`gauss_newton_metric`) and the robust score that ranks its hypotheses
(:func:`robust_score`).

The Chamfer distance is that of H. G. Barrow, J. M. Tenenbaum, R. C. Bolles and H. C. Wolf, "Parametric
correspondence and chamfer matching: Two new techniques for image matching", IJCAI 1977; the robust rho is the
Geman-McClure loss (S. Geman and D. E. McClure, "Statistical methods for tomographic image reconstruction",
Bulletin of the International Statistical Institute 52(4), 1987); point-to-plane distances are those of Y.
Chen and G. Medioni, "Object modelling by registration of multiple range images", Image and Vision Computing
10(3), 1992; the Gauss-Newton metric is J^T J of the residuals (J. Nocedal and S. J. Wright, "Numerical
Optimization", Springer, 2nd ed., 2006, chapter 10).
"""

from __future__ import annotations

import numpy as np
import torch

from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common.nearest import PointTree
from bodyfit.models.fitting.common.surface import NormalOperators, coarse_faces, vertex_normals
from bodyfit.models.fitting.registered.fitter import DataTerm
from bodyfit.models.fitting.scan.config import ScanPhase
from bodyfit.models.fitting.scan.hypotheses import HypothesisSteps
from bodyfit.models.fitting.scan.limb_search import Hypotheses

# In the point-to-plane phases, a model vertex further than this from every fit point adds a constant to the
# model -> scan term: it lies over a hole (or where a single view saw nothing), and the nearest point, on
# the hole's rim, would pull heads and hands over holes out of place.
REACH_MM = 25.0

# the vertex sets a point-to-plane phase can fit: their faces (F, 3) and normal operators
Surfaces = dict[str, tuple[np.ndarray, NormalOperators]]


def plane_surfaces(
    model: BodyModel, dense: np.ndarray, normals: NormalOperators, loop_float: type[np.floating]
) -> Surfaces:
    """The surfaces of the vertex sets a point-to-plane phase can fit: "all" (the model's faces and their
    normal operators ``normals``) and "dense" (the coarse mesh on the vertices ``dense``, its operators in
    ``loop_float``)."""
    faces = np.asarray(model.data["faces"], np.int64)
    dense_faces = coarse_faces(model.data["vertices_mean"], faces, dense)
    return {
        "all": (faces, normals),
        "dense": (dense_faces, NormalOperators.of(dense_faces, len(dense), loop_float)),
    }


def geman_mcclure(
    d2: torch.Tensor, s2: float, c2: float = 0.0, outside: torch.Tensor | None = None
) -> torch.Tensor:
    """The Geman-McClure rho of squared distances ``d2`` (any shape): d2 s2 / (d2 + s2); with ``c2`` > 0, the
    entries ``outside`` (bool, same shape) take the scale c2 instead (the one-sided loss's clothing side)."""
    if outside is None or not c2:
        return d2 * s2 / (d2 + s2)
    scale = torch.where(outside, torch.as_tensor(c2, dtype=d2.dtype), torch.as_tensor(s2, dtype=d2.dtype))
    return d2 * scale / (d2 + scale)


def chamfer_term(
    hyp: Hypotheses, phase: ScanPhase, dtype: torch.dtype, tangential: float, surfaces: Surfaces
) -> DataTerm:
    """The robust two-way Chamfer loss of every hypothesis on the stage's vertices (H, V', 3) in mm:

        mean_i rho(|v_j(i) - p_i|) + 0.5 mean_j rho(|v_j - s(j)|),  rho(d) = d^2 s^2 / (d^2 + s^2)

    with p_i the phase's fit points, j(i) the vertex nearest p_i, s(j) the fit point nearest v_j (both
    found again at every evaluation), and the scan -> model distance point-to-plane when
    ``phase.plane`` (the normals of the stage's vertex set's surface in ``surfaces``, the in-plane
    directions weighted by ``tangential``); then a vertex further than :data:`REACH_MM` from every fit
    point adds a constant to the second mean. Computed in ``dtype``.

    With ``phase.cloth_sigma_mm`` (a point-to-plane phase) the loss is one-sided, for a body under loose
    clothing: a pair whose scan point lies outside the body (along the vertex's normal) takes that smaller
    scale s, so that cloth standing off the body pulls it out hardly at all, while a body surface outside
    the scan points keeps the phase's scale and is pulled in. Near zero both sides are d^2, so where the
    cloth lies on the skin the body fits it as closely as without it. The idea of fitting the body inside
    the clothing, close to the scan where the cloth is tight, is that of A. O. Balan and M. J. Black, "The
    Naked Truth: Estimating Body Shape Under Clothing", European Conference on Computer Vision (ECCV), 2008,
    and C. Zhang, S. Pujades, M. J. Black and G. Pons-Moll, "Detailed, Accurate, Human Shape Estimation
    From Clothed 3D Scan Sequences", Conference on Computer Vision and Pattern Recognition (CVPR), 2017."""
    P = torch.as_tensor(hyp.points * 1000.0, dtype=dtype)
    fit_points = hyp.points
    point_trees = [PointTree(p) for p in fit_points]
    s2 = phase.sigma_mm**2
    plane = phase.plane
    if plane and phase.stage.vertices not in surfaces:
        raise ValueError(
            f"point-to-plane Chamfer needs a vertex set with a surface ({', '.join(surfaces)}); "
            f"the stage {phase.stage.name!r} fits {phase.stage.vertices!r}"
        )
    faces, normal_ops = surfaces.get(phase.stage.vertices, surfaces["all"])

    c2 = phase.cloth_sigma_mm**2

    def rho(d2: torch.Tensor, outside: torch.Tensor | None = None) -> torch.Tensor:
        return geman_mcclure(d2, s2, c2, outside)

    seen = None if hyp.visible is None else torch.as_tensor(hyp.visible, dtype=dtype)
    seen_index = None if hyp.visible is None else [np.flatnonzero(m) for m in hyp.visible]

    def term(verts_mm: torch.Tensor) -> torch.Tensor:
        v = verts_mm.detach().double().numpy() / 1000.0
        H = len(v)
        pairs = np.empty(fit_points.shape[:2], np.int64)
        targets = np.empty(v.shape)
        for h in range(H):
            if seen_index is None:
                pairs[h] = PointTree(v[h]).query(fit_points[h])[1]
            else:  # a single view's points lie on the surface that faced the sensor
                pairs[h] = seen_index[h][PointTree(v[h, seen_index[h]]).query(fit_points[h])[1]]
            targets[h] = fit_points[h][point_trees[h].query(v[h])[1]]
        J = torch.as_tensor(pairs).unsqueeze(-1).expand(-1, -1, 3)
        r = torch.gather(verts_mm, 1, J) - P  # (H, N, 3)
        d2 = (r**2).sum(-1)
        to_target = verts_mm - torch.as_tensor(targets * 1000.0, dtype=dtype)
        cloth = m2s_cloth = None  # the pairs whose scan point lies outside the body: the clothing side
        if plane:
            n = vertex_normals(verts_mm.detach().numpy(), faces, normal_ops)  # float32
            along = (r * torch.as_tensor(np.take_along_axis(n, pairs[..., None], 1), dtype=dtype)).sum(-1)
            d2 = along**2 + tangential * (d2 - along**2)
            if c2:
                cloth = along.detach() < 0.0
                m2s_cloth = (to_target.detach() * torch.as_tensor(n, dtype=dtype)).sum(-1) < 0.0
        m2s = rho((to_target**2).sum(-1), m2s_cloth)
        if plane:  # beyond the reach, a constant: no pull towards a hole's rim
            reach = torch.full_like(m2s, REACH_MM**2)
            cap = REACH_MM**2 * s2 / (REACH_MM**2 + s2)
            m2s = m2s.clamp_max(cap) if m2s_cloth is None else torch.minimum(m2s, rho(reach, m2s_cloth))
        m2s_mean = m2s.mean(1) if seen is None else (m2s * seen).sum(1) / seen.sum(1).clamp_min(1.0)
        return (rho(d2, cloth).mean(1) if phase.two_way else 0.0) + 0.5 * m2s_mean

    return term


def robust_score(verts: np.ndarray, hyp: Hypotheses, phase: ScanPhase, tree: PointTree) -> np.ndarray:
    """(H,) each hypothesis's robust Chamfer score (rho / sigma^2, lower is better) of its vertices ``verts``
    (H, V', 3, body frames) against its fit points and the cleaned scan's ``tree`` (a single view's on the
    vertices facing its sensor, ``hyp.visible``)."""
    sigma = phase.sigma_mm / 1000.0
    score = np.empty(len(verts))
    for h, v in enumerate(verts):
        if hyp.visible is not None:
            v = v[hyp.visible[h]]
        d_s = PointTree(v).query(hyp.points[h])[0]
        d_m = tree.query(v @ hyp.rotation[h] + hyp.centre)[0]
        score[h] = 0.5 * (d_m**2 / (d_m**2 + sigma**2)).mean()
        if phase.two_way:
            score[h] += (d_s**2 / (d_s**2 + sigma**2)).mean()
    return score


def gauss_newton_metric(
    steps: HypothesisSteps, hyp: Hypotheses, phase: ScanPhase, damping: float, tangential: float
) -> torch.Tensor:
    """(H, P, P) the Gauss-Newton metric of ``phase``'s loss (its stage's variables) at each hypothesis's
    current state (:meth:`RegisteredFitter.metric` of ``steps.fitter`` on the vertex subset,
    ``regularise=damping``; for a point-to-plane phase the normal direction weighted fully and the in-plane
    ones by ``tangential``): the phase's L-BFGS runs in the variables it makes the identity."""
    fitter = steps.fitter
    if not phase.plane:
        return fitter.metric(phase.stage, hyp.state, "subset", regularise=damping)
    index = fitter.index["subset"]
    normals = vertex_normals(steps.vertices(hyp.state), steps.faces, steps.normals)[:, index]
    return fitter.metric(phase.stage, hyp.state, "subset", normals, tangential, damping)

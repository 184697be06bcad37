"""Build one person's rig from several registered scans of them in different poses.

The method follows P. Fechteler, A. Hilsmann and P. Eisert, "Example-based Body Model Optimization and
Skinning", Eurographics 2016 Short Papers: the person's template vertices (sparse least squares with a
mesh-Laplacian term), skinning weights and joint positions are solved in turn, alternating with the poses of
all example scans, until the model resembles every scan. Here the template is our shape space's body for one
shared coefficient vector plus per-vertex rest-pose offsets
(:func:`bodyfit.models.fitting.sequence.offsets.fit_rest_offsets`, as in SMPL+D), the weights are solved
per vertex (:mod:`.weights`) and the joints as offsets to the segment scales (:mod:`.joints`), so the
skeleton stays the shape space's OpenSim-valid one:

1. each scan is fitted alone (:class:`RegisteredFitter`, its own shape: the generic model's error);
2. the joints the scans' poses leave undetermined are named (:func:`undetermined_joints`);
3. one shape for all scans and a pose per scan are fitted; then, ``rounds`` times, the offsets, the weights
   and the joints are solved against the fit in turn and the shape and poses refitted with them;
4. a scan the rig explains far worse than the others is of another person (:func:`strangers`): refused.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from bodyfit.models.body.model import BodyDecoder, BodyModel
from bodyfit.models.errors import BodyfitError, ShapeError
from bodyfit.models.fitting.registered.fitter import BodyFit, RegisteredFitter
from bodyfit.models.fitting.registered.stages import DEFAULT_STAGES, RegisteredFitConfig, ShapeSet
from bodyfit.models.fitting.sequence.offsets import OffsetConfig, offsets_of_fit
from bodyfit.models.rig.fit import with_decoder
from bodyfit.models.rig.icp import ClosestConfig, closest_targets, fit_to_points, normal_part
from bodyfit.models.rig.joints import JointConfig, solve_joints
from bodyfit.models.rig.subject import PersonalParts, Subject, model_fingerprint
from bodyfit.models.rig.weights import (
    WeightConfig,
    adjacency,
    body_adjacency,
    candidate_bodies,
    skinning_columns,
    solve_weights,
)

LIMB_JOINTS = (
    "hip_r", "hip_l", "walker_knee_r", "walker_knee_l", "ankle_r", "ankle_l",
    "acromial_r", "acromial_l", "elbow_r", "elbow_l",
)  # fmt: skip
"""The joints whose centres set the limbs' proportions: each must bend between the scans to be observed."""
REFIT_STAGES = tuple(stage for stage in DEFAULT_STAGES if stage.shape == "all")
"""The registered fitter's whole-body stages: the refits after each offset solve start from the last fit."""


class RigError(BodyfitError):
    """Scans that cannot make one person's rig: too few, of different people, or poses too alike."""


@dataclass(frozen=True, kw_only=True)
class RigConfig:
    """min_scans: scans needed; rounds: alternations; offsets: their smoothness and stiffness; weights,
    joints: how the person's skinning weights and joint centres are solved (None: the body model's);
    closest: the closest-point pairing of raw scans and its rounds;
    stranger_mm, stranger_factor: a scan the rig misses by more than both ``stranger_mm`` and
    ``stranger_factor`` times the median scan's error is of another person; min_motion_deg: how far a limb
    joint must move between two scans to be observed; allow_undetermined: build anyway when some are not
    (their centres then come from the shape space alone)."""

    min_scans: int = 3
    rounds: int = 4
    offsets: OffsetConfig = field(default_factory=lambda: OffsetConfig(smoothness=0.3, stiffness=1e-3))
    weights: WeightConfig | None = field(default_factory=WeightConfig)
    joints: JointConfig | None = field(default_factory=JointConfig)
    closest: ClosestConfig = field(default_factory=ClosestConfig)
    stranger_mm: float = 3.0
    stranger_factor: float = 2.5
    min_motion_deg: float = 15.0
    allow_undetermined: bool = False


@dataclass(frozen=True)
class RigBuild:
    """The subject, each scan's mean vertex error (mm) under the generic model (its own shape) and under the
    rig, the undetermined joints (built anyway: ``allow_undetermined``), and the seconds it took."""

    subject: Subject
    generic_mm: np.ndarray
    personal_mm: np.ndarray
    undetermined: tuple[str, ...]
    seconds: float


def strangers(personal_mm: np.ndarray, floor_mm: float, factor: float) -> list[int]:
    """Indices of the scans the rig explains worse than ``floor_mm`` and ``factor`` times the median scan:
    one person's rig fits all their poses alike (its offsets are shared), so a scan it cannot follow shows
    someone else (a body that differs beyond the fits' error)."""
    limit = max(floor_mm, factor * float(np.median(personal_mm)))
    return [k for k in range(len(personal_mm)) if personal_mm[k] > limit]


def undetermined_joints(model: BodyModel, poses: np.ndarray, min_motion_deg: float) -> list[str]:
    """The :data:`LIMB_JOINTS` none of whose coordinates spans ``min_motion_deg`` over poses (K, n_dof)."""
    spans = np.degrees(poses.max(axis=0) - poses.min(axis=0))
    names = model.dof_names
    out = []
    for joint in LIMB_JOINTS:
        idx = [names.index(c.name) for c in model.skeleton.spec.coordinates if c.joint == joint]
        if idx and spans[idx].max() < min_motion_deg:
            out.append(joint)
    return out


def build_rig(
    model: BodyModel,
    registrations: np.ndarray,
    names: Sequence[str] = (),
    weights: np.ndarray | None = None,
    config: RigConfig | None = None,
    points: Sequence[np.ndarray | None] | None = None,
) -> RigBuild:
    """One person's rig from K registrations (K, V, 3) metres in our topology, any placement, with per-vertex
    weights (K, V) (0 = unseen; default ones); ``names`` name the scans in messages and the subject file.
    ``points``: for each scan, the raw scan's points (N_k, 3) in the frame of its registration, or None for
    a scan given in our topology: the rig is then refined by closest points over all raw scans
    (:mod:`.icp`).

    Raises:
        ShapeError: wrong array shapes. RigError: fewer than ``min_scans`` scans, scans of different people
        (named), or poses that leave limb joints undetermined (named, with how to fix it).
    """
    cfg = config or RigConfig()
    began = time.perf_counter()
    x = np.asarray(registrations, np.float64)
    labels = list(names) or [f"scan {k}" for k in range(len(x))]
    if x.ndim != 3 or len(labels) != len(x):
        raise ShapeError(
            f"registrations must be (K, V, 3) with one name each; got {x.shape}, {len(labels)} names"
        )
    if len(x) < cfg.min_scans:
        raise RigError(
            f"a rig needs at least {cfg.min_scans} scans of the person in different poses; got {len(x)}"
        )
    if points is not None and (
        len(points) != len(x) or any(p is not None and (p.ndim != 2 or p.shape[1] != 3) for p in points)
    ):
        raise ShapeError(f"points must be one (N, 3) array or None per registration ({len(x)})")
    fitter = RegisteredFitter(model)
    x, w = fitter.validate(x, weights)
    alone = fitter.fit(x, w)
    undetermined = undetermined_joints(model, alone.coordinates, cfg.min_motion_deg)
    if undetermined and not cfg.allow_undetermined:
        raise RigError(
            f"the scans' poses leave these joints undetermined: {', '.join(undetermined)}; each needs two "
            f"scans whose angles at it differ by {cfg.min_motion_deg:g} degrees or more (add scans with them "
            "bent), or allow it (`--allow-undetermined`: their centres then come from the shape space alone)"
        )
    fit, parts = _alternate(model, fitter, x, w, alone, cfg, points)
    generic = _mean_mm(alone)
    personal = _mean_mm(fit)
    others = strangers(personal, cfg.stranger_mm, cfg.stranger_factor)
    if others:
        missed = ", ".join(f"{labels[k]} ({personal[k]:.1f} mm)" for k in others)
        raise RigError(
            f"{missed}: another person than the other scans (the rig fits the rest to "
            f"{np.median(personal):.1f} mm); pass scans of one person only"
        )
    report = {"generic_mm": float(generic.mean()), "personal_mm": float(personal.mean())}
    subject = Subject(
        fit.shape[0],
        parts.offsets,
        model_fingerprint(model),
        fit.coordinates,
        fit.root,
        tuple(labels),
        report,
        weights=parts.weights,
        scale_offsets=parts.scale_offsets,
    )
    return RigBuild(subject, generic, personal, tuple(undetermined), time.perf_counter() - began)


def _alternate(
    model: BodyModel,
    fitter: RegisteredFitter,
    x: np.ndarray,
    w: np.ndarray,
    alone: BodyFit,
    cfg: RigConfig,
    points: Sequence[np.ndarray | None] | None = None,
) -> tuple[BodyFit, PersonalParts]:
    """One shape and K poses (started from each scan's own fit, ``alone``), then ``rounds`` of: offsets
    against the residuals, weights, joints (each with the others fixed), and a refit of the shape and poses
    with them. With raw ``points`` (one (N_k, 3) array or None per scan), the shape prior is
    ``cfg.closest.shape_prior``, the shape and poses are fitted to the raw scans' points together first
    (:func:`.icp.fit_to_points`, the registered scans sitting at their own fit), and ``cfg.closest.rounds``
    rounds follow, each scan's targets re-paired with its points first (:func:`.icp.closest_targets`), and
    after the rounds ``cfg.closest.repose_after`` the raw scans' poses alone fitted to their points again
    through the person's rig."""
    raw = points is not None and any(p is not None for p in points)
    if raw:
        fitter = RegisteredFitter(model, replace(fitter.config, shape_prior=cfg.closest.shape_prior))
    fit = fitter.fit(x, w, init=alone, shared_shape=True)
    if raw:
        solver = _PartSolver(model, cfg, cfg.closest.shape_prior, cfg.closest.offset_tangential)
    else:
        solver = _PartSolver(model, cfg)
    if raw and points is not None and cfg.closest.chamfer_iterations > 0:
        fit = _fit_raw(fitter, fit, points, cfg.closest)
    parts = PersonalParts.generic(model)
    for round_ in range(cfg.closest.rounds if raw else cfg.rounds):
        targets, confidence = x, w
        if raw and points is not None:
            targets, confidence = _closest(model, fit, x, w, points, cfg.closest)
        parts, fit = solver.solve(parts, fit, targets, confidence)
        personal = with_decoder(solver.refitter, parts.decoder(model, solver.refitter.config.dtype))
        fit = personal.fit(targets, confidence, init=fit, shared_shape=True)
        if raw and points is not None and round_ in cfg.closest.repose_after:
            close, decoder = cfg.closest, parts.decoder(model, torch.float64)
            fit = _fit_raw(personal, fit, points, close, "none", close.repose_iterations, decoder)
    return fit, parts


def _fit_raw(
    fitter: RegisteredFitter,
    fit: BodyFit,
    points: Sequence[np.ndarray | None],
    config: ClosestConfig,
    shape: ShapeSet = "all",
    iterations: int | None = None,
    decoder: BodyDecoder | None = None,
) -> BodyFit:
    """``fit`` (shared shape) with the raw scans' poses, and its shape unless ``shape`` is ``"none"``,
    fitted to their points together (:func:`.icp.fit_to_points`, ``iterations`` L-BFGS iterations, None:
    ``config.chamfer_iterations``) through ``fitter``'s decoder; the scans given in our topology keep their
    poses (they carry their own correspondence, which the refits that follow use). ``decoder``: the same
    body in float64 for the answer's vertices and joints (None: the body model's)."""
    scans = [(k, p) for k, p in enumerate(points) if p is not None]
    raw = [k for k, _ in scans]
    start = BodyFit(fit.shape[raw], fit.coordinates[raw], fit.root[raw], fit.vertices[raw], fit.joints[raw])
    moved = fit_to_points(fitter, [p for _, p in scans], start, config, shape, iterations)
    q, r = fit.coordinates.copy(), fit.root.copy()
    q[raw], r[raw] = moved.coordinates, moved.root
    c = np.tile(moved.shape[0], (len(q), 1))
    decode = decoder or fitter.model.decoder(torch.float64)
    with torch.no_grad():
        v, joints, _, _ = decode(*(torch.as_tensor(a) for a in (c, q, r)))
    return replace(fit, shape=c, coordinates=q, root=r, vertices=v.numpy(), joints=joints.numpy())


def _closest(
    model: BodyModel,
    fit: BodyFit,
    x: np.ndarray,
    w: np.ndarray,
    points: Sequence[np.ndarray | None],
    config: ClosestConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Targets (K, V, 3) and confidences (K, V): each raw scan's closest-point targets from the rig posed
    as ``fit`` has it, the registered scans' own vertices and weights."""
    targets, confidence = x.copy(), w.copy()
    for k, scan in enumerate(points):
        if scan is not None:
            targets[k], confidence[k] = closest_targets(fit.vertices[k], model.faces, scan, config)
            if confidence[k].sum() <= 0:
                targets[k], confidence[k] = x[k], w[k]  # no point near the rig: its registration stands
    return targets, confidence


class _PartSolver:
    """One round's solves of the person's parts with the poses fixed: template offsets against the
    residuals, then the skinning weights, then the joints (each with the others fixed); ``refitter`` the
    shape and pose refits' fitter (its shape prior ``shape_prior``, None: the registered fitter's);
    ``tangential``: the share of each offset step kept along the template's surface (:func:`.icp.normal_part`;
    1 for registered scans, whose correspondence places every vertex along the surface too)."""

    def __init__(
        self, model: BodyModel, cfg: RigConfig, shape_prior: float | None = None, tangential: float = 1.0
    ) -> None:
        self.model, self.cfg, self.tangential = model, cfg, tangential
        fits = RegisteredFitConfig(stages=REFIT_STAGES)
        self.refitter = RegisteredFitter(
            model, fits if shape_prior is None else replace(fits, shape_prior=shape_prior)
        )
        self.neighbours = adjacency(model.faces, model.n_vertices)
        self.candidates = None
        if cfg.weights is not None:
            generic = np.asarray(model.data["weights"], np.float64)
            bodies = (
                body_adjacency(model.skeleton.spec)
                if cfg.weights.jointed
                else np.eye(generic.shape[1], dtype=bool)
            )
            rings, floor = cfg.weights.rings, cfg.weights.floor
            self.candidates = candidate_bodies(generic, self.neighbours, bodies, rings, floor)

    def solve(
        self, parts: PersonalParts, fit: BodyFit, x: np.ndarray, w: np.ndarray
    ) -> tuple[PersonalParts, BodyFit]:
        """The parts after one round against targets x (K, V, 3) with confidences w (K, V), at ``fit``, and
        the fit with the poses the joints were solved with."""
        model, cfg = self.model, self.cfg
        decoder = parts.decoder(model)
        step = offsets_of_fit(decoder, fit, x, w, model.faces, cfg.offsets)
        if self.tangential != 1.0:
            step = normal_part(step, _rest(model, decoder, fit.shape[0]), model.faces, self.tangential)
        parts = replace(parts, offsets=parts.offsets + step)
        if cfg.weights is not None and self.candidates is not None:
            columns, _ = skinning_columns(
                parts.decoder(model), fit.shape[0], fit.coordinates, fit.root, model.bind_coordinates
            )
            weights = solve_weights(
                columns, x, w, parts.weights, self.candidates, self.neighbours, cfg.weights
            )
            parts = replace(parts, weights=weights)
        if cfg.joints is not None:
            scales, q, r = solve_joints(
                model, parts, fit.shape[0], fit.coordinates, fit.root, x, w, cfg.joints
            )
            parts = replace(parts, scale_offsets=scales)
            fit = replace(fit, coordinates=q, root=r)
        return parts, fit


def _rest(model: BodyModel, decoder: BodyDecoder, shape: np.ndarray) -> np.ndarray:
    """The template (V, 3) metres of ``decoder`` for coefficients ``shape`` (n_shape,), in the bind pose."""
    dtype = decoder.bind_rot_t.dtype
    with torch.no_grad():
        c = torch.as_tensor(shape[None], dtype=dtype)
        q = torch.as_tensor(model.bind_coordinates[None], dtype=dtype)
        return decoder(c, q, torch.zeros(1, 3, dtype=dtype))[0][0].double().numpy()


def _mean_mm(fit: BodyFit) -> np.ndarray:
    """Each mesh's mean vertex error (K,) in mm, over its vertices with weight, as the fit reports it."""
    return np.array([report.distances.mean for report in fit.reports])

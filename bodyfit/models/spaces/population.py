"""A body model's shape space recomputed from a population of bind-pose registrations (BLiSS section 3.2,
with the bone-level split of BLSM).

The population holds, per body, its mesh in the model's bind pose (V, 3) and its skeleton's segment scales
(n_seg, 3). The new space is built the way the shipped one is (:mod:`bodyfit.models.body.build`, step d): a
bone PCA of the segment scales, bone-corrective blendshapes fitted by least squares, an identity PCA of what
the mean and the correctives leave, and a non-negative joint regressor refitted on the population's meshes
and joint centres. The bone and identity parts stay separate, so a coefficient vector still places the
skeleton by its bone part and the skin by both, and the skeleton keeps following the bones.

BLiSS: S. Muralikrishnan, C.-H. P. Huang, D. Ceylan and N. J. Mitra, "BLiSS: Bootstrapped Linear Shape
Space", International Conference on 3D Vision (3DV), 2024.
BLSM: H. Wang, R. A. Güler, I. Kokkinos, G. Papandreou and S. Zafeiriou, "BLSM: A Bone-Level Skinned Model
of the Human Mesh", European Conference on Computer Vision (ECCV), 2020.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bodyfit.models.body.model import BodyModel, body_points, joint_anchors
from bodyfit.models.body.shape_space import fit_correctives, fit_joint_regressor, fit_pca
from bodyfit.models.fitting.common.surface import vertex_normals

# Arrays of body.npz that a recomputed shape space replaces; every other array (faces, skinning weights,
# bind pose, landmarks, mirror map, bone geometry) carries over from the model the space grew from.
SPACE_ARRAYS = (
    "vertices_mean",
    "scale_mean",
    "scale_basis",
    "bone_correctives",
    "identity_basis",
    "joint_regressor",
    "template",
    "heldout_shape",
)


@dataclass(frozen=True)
class Population:
    """N bodies of one topology: ``meshes`` (N, V, 3) in the bind pose, ``scales`` (N, n_seg, 3) the
    segment scales of their skeletons; metres."""

    meshes: np.ndarray
    scales: np.ndarray

    def __len__(self) -> int:
        return len(self.meshes)

    def __add__(self, other: Population) -> Population:
        return Population(
            np.concatenate([self.meshes, other.meshes]), np.concatenate([self.scales, other.scales])
        )

    def take(self, index: np.ndarray) -> Population:
        return Population(self.meshes[index], self.scales[index])


def rest_meshes(data: dict[str, np.ndarray], shape: np.ndarray) -> np.ndarray:
    """Bind-pose templates (N, V, 3) of shape coefficients (N, n_bone + n_identity): V_mean + c_b P_bc +
    c_s P_s (BLSM eq. 1, 7, 8), float64."""
    n_bone = data["scale_basis"].shape[0]
    c = np.asarray(shape, np.float64)
    mean = np.asarray(data["vertices_mean"], np.float64)
    bone = np.einsum("nk,kvc->nvc", c[:, :n_bone], np.asarray(data["bone_correctives"], np.float64))
    ident = np.einsum("nk,kvc->nvc", c[:, n_bone:], np.asarray(data["identity_basis"], np.float64))
    return np.asarray(mean + bone + ident)


def segment_scales(data: dict[str, np.ndarray], shape: np.ndarray) -> np.ndarray:
    """Segment scales (N, n_seg, 3) of shape coefficients (N, n_shape): s_mean + c_b P_b (BLSM eq. 4)."""
    n_bone = data["scale_basis"].shape[0]
    c_b = np.asarray(shape, np.float64)[:, :n_bone]
    basis = np.asarray(data["scale_basis"], np.float64)
    return np.asarray(data["scale_mean"], np.float64) + np.einsum("nk,ksc->nsc", c_b, basis)


def sample_population(model: BodyModel, n: int, seed: int) -> Population:
    """``n`` bodies of the model's own space (shape coefficients drawn from N(0, 1), the model's population
    distribution) in the bind pose: the registrations a space starts from when no others are given."""
    shape = np.random.default_rng(seed).normal(size=(n, model.n_shape))
    return Population(rest_meshes(model.data, shape), segment_scales(model.data, shape))


def bind_joints(model: BodyModel, scales: np.ndarray) -> np.ndarray:
    """Anatomical joint centres (N, J, 3) in the bind pose of skeletons with segment scales (N, n_seg, 3)."""
    skeleton = model.skeleton
    fk = skeleton.kinematics(torch.float64)
    s = torch.as_tensor(np.asarray(scales, np.float64))
    q = torch.as_tensor(model.bind_coordinates).expand(len(s), -1)
    with torch.no_grad():
        frames = fk(q, None, s).frames
    bodies, local = joint_anchors(skeleton.spec)
    seg_of_body = np.asarray(skeleton.spec.body_segment_index)
    joints = body_points(
        frames, s, torch.as_tensor(bodies), torch.as_tensor(seg_of_body[bodies]), torch.as_tensor(local)
    )
    return np.asarray(joints.numpy())


def symmetric(meshes: np.ndarray, mirror: np.ndarray) -> np.ndarray:
    """Meshes (N, V, 3) averaged with their mirror images across the sagittal plane (z -> -z), as the
    shipped space's population is: the skeleton and the skinning are symmetric."""
    return np.asarray(0.5 * (meshes + meshes[:, mirror] * np.array([1.0, 1.0, -1.0])))


def recompute_space(
    model: BodyModel, population: Population, n_bone: int | None = None, n_identity: int | None = None
) -> dict[str, np.ndarray]:
    """The arrays of a ``body.npz`` whose shape space is learned from ``population`` (BLiSS section 3.2: PCA
    of the registrations; BLSM 3.1-4.3: bone PCA, bone correctives, identity PCA of the residual), with
    ``n_bone`` and ``n_identity`` coefficients (default: the model's, so both spaces have the same count).
    Every array outside :data:`SPACE_ARRAYS` is the model's; float32 like the shipped assets."""
    n_bone = model.n_bone if n_bone is None else n_bone
    n_identity = model.n_identity if n_identity is None else n_identity
    N, V, _ = population.meshes.shape
    n_seg = population.scales.shape[1]
    bone = fit_pca(population.scales.reshape(N, n_seg * 3), n_bone)
    c_bone = bone.project(population.scales.reshape(N, n_seg * 3))
    flat = population.meshes.reshape(N, V * 3)
    correctives = fit_correctives(flat, c_bone)
    mean = flat.mean(axis=0)
    residual = flat - mean - c_bone @ correctives
    identity = fit_pca(residual, n_identity)
    joints = bind_joints(model, population.scales)
    data = dict(model.data)
    data.update(
        vertices_mean=mean.reshape(V, 3),
        scale_mean=bone.mean.reshape(n_seg, 3),
        scale_basis=bone.basis.reshape(-1, n_seg, 3),
        bone_correctives=correctives.reshape(-1, V, 3),
        identity_basis=identity.basis.reshape(-1, V, 3),
        joint_regressor=fit_joint_regressor(population.meshes, joints),
        heldout_shape=np.concatenate([c_bone[:4], identity.project(residual[:4])], axis=1),
    )
    data = {k: v.astype(np.float32) if v.dtype.kind == "f" else v for k, v in data.items()}
    # The mesh users get at zero parameters, as the build stores it.
    data["template"] = BodyModel(model.skeleton, data).forward(dtype=torch.float64).vertices[0].numpy()
    data["template"] = data["template"].astype(np.float32)
    return data


def space_basis(data: dict[str, np.ndarray], k: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The span of a space's templates with its first ``k`` coefficients (bone first, then identity, as the
    build's reconstruction curve counts them; default all): mean (V * 3,) and basis (k, V * 3)."""
    correctives = np.asarray(data["bone_correctives"], np.float64)
    identity = np.asarray(data["identity_basis"], np.float64)
    basis = np.concatenate([correctives, identity]).reshape(len(correctives) + len(identity), -1)
    k = len(basis) if k is None else k
    return np.asarray(data["vertices_mean"], np.float64).reshape(-1), basis[:k]


def parametric_errors(
    data: dict[str, np.ndarray], meshes: np.ndarray, faces: np.ndarray, k: int | None = None
) -> dict[str, float]:
    """How well a space explains bind-pose meshes (N, V, 3): each is replaced by its least-squares
    coefficients' template (the best any fit in this space can do; BLiSS Table 2's "PCA only"), with ``k``
    coefficients (default all). Returns the mean vertex-to-vertex and vertex-to-plane distances (mm; the
    plane at each vertex of the reconstruction, normals from ``faces`` (F, 3)) and the v2v in cm, BLiSS's
    unit."""
    mean, basis = space_basis(data, k)
    target = np.asarray(meshes, np.float64).reshape(len(meshes), -1)
    coef, *_ = np.linalg.lstsq(basis.T, (target - mean).T, rcond=None)
    recon = (mean + coef.T @ basis).reshape(meshes.shape)
    diff = np.asarray(meshes, np.float64) - recon
    v2v = float(np.linalg.norm(diff, axis=-1).mean()) * 1e3
    normals = np.stack([vertex_normals(r, faces) for r in recon])
    v2p = float(np.abs((diff * normals).sum(-1)).mean()) * 1e3
    return {"v2v_mm": round(v2v, 3), "v2p_mm": round(v2p, 3), "v2v_cm": round(v2v / 10.0, 4)}

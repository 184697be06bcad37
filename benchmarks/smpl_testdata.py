"""Test data in SMPL's formats, made from open sources only (no SMPL file or data may be redistributed).

* :func:`build_smpl_like_model`: an SMPL-format model file (SMPL's 24-joint tree and key names) whose
  template is the CC BY 4.0 body ``data/smpl_ccby/human_man.obj`` (SMPL topology); shape directions are a
  PCA of our model's population (learned from anny's) carried onto that topology; the joint regressor is
  fitted (non-negative, each joint's weights summing to one) to SMPL-like joint locations taken from our
  anatomical joints; skinning weights are ours, carried over and summed per SMPL joint; pose correctives
  are zero. It exercises path (a) end to end.
* :func:`smpl_poses_from_ours`: SMPL axis-angle poses and translations reproducing our posed bodies (each
  SMPL joint follows the rotation of one of our bodies from the T-pose; the elbows also carry the forearm's
  twist, :func:`forearm_twist`), so CMU motion retargeted onto our skeleton becomes an AMASS-style sequence
  (:func:`cmu_smpl_sequence`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.optimize import nnls
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from bodyfit.io.bvh import CMU_UNITS, read_bvh
from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common.surface import closest_on_surface, vertex_normals
from bodyfit.models.fitting.registered.fitter import RegisteredFitter
from bodyfit.models.fitting.registered.smpl_topology import (
    SMPL_TO_BODY,
    SOURCE_DIR,
    fit_smpl_meshes,
    read_obj,
)
from bodyfit.models.fitting.retarget.fitter import retarget
from bodyfit.models.upgrade.smpl_joints import SMPL_JOINTS, SMPL_PARENTS, smpl_joint_locations
from bodyfit.models.upgrade.smpl_model import SmplModel

# The body of ours whose rotation each SMPL joint follows (and whose skin it moves).
FOLLOWS = (
    "pelvis", "femur_l", "femur_r", "torso", "tibia_l", "tibia_r", "thoracic_link", "talus_l", "talus_r",
    "thorax", "toes_l", "toes_r", "cervical_link", "scapula_l", "scapula_r", "head", "humerus_l",
    "humerus_r", "ulna_l", "ulna_r", "hand_l", "hand_r", "hand_l", "hand_r",
)  # fmt: skip
SKIN = {"patella_l": 4, "patella_r": 5, "calcn_l": 7, "calcn_r": 8, "radius_l": 18, "radius_r": 19,
        "scapulothoracic_link_l": 13, "scapulothoracic_link_r": 14}  # fmt: skip
REGRESSOR_NEIGHBOURS = 200
"""Vertices nearest each joint that its regressor mixes. A joint deep inside the body (the lumbar and
thoracic joints, the hips) lies inside the convex hull of the skin around it only when the neighbourhood
reaches the opposite side of the trunk or limb: with 40 the regressed spine joints sat 6-10 cm off ours, so
the LBS mesh turned its trunk about the wrong points and read as a tilted pelvis."""
REGRESSOR_SUM_WEIGHT = 1e3
"""Weight of the row that holds each joint's regressor weights at a sum of one (a convex combination, as
SMPL's regressor is), inside the non-negative least squares rather than by rescaling after it."""


def _carry(
    model: BodyModel, fitted: np.ndarray, target: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Express ``target`` points (N, 3) on our fitted surface: face (N,), barycentric (N, 3), offset (N,)
    along the interpolated normal."""
    faces = model.faces
    face, bary, _ = closest_on_surface(target, fitted, faces)
    foot = np.einsum("nk,nkd->nd", bary, fitted[faces[face]])
    normal = np.einsum("nk,nkd->nd", bary, vertex_normals(fitted, faces)[faces[face]])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return face, bary, np.einsum("nd,nd->n", target - foot, normal)


def _apply(
    model: BodyModel, verts: np.ndarray, face: np.ndarray, bary: np.ndarray, offset: np.ndarray
) -> np.ndarray:
    """Our meshes (B, V, 3) -> the carried points (B, N, 3)."""
    tri = model.faces[face]
    normals = np.stack([vertex_normals(v, model.faces) for v in verts])
    n = np.einsum("nk,bnkd->bnd", bary, normals[:, tri])
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    return np.einsum("nk,bnkd->bnd", bary, verts[:, tri]) + offset[None, :, None] * n


def build_smpl_like_model(
    model: BodyModel, n_population: int = 60, n_betas: int = 10, seed: int = 0
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The SMPL-format model file's arrays (SMPL key names) and what was fitted (shape, pose, root of our
    model on the template body) for :func:`smpl_poses_from_ours`."""
    v_smpl, f_smpl = read_obj(SOURCE_DIR / "human_man.obj")
    S = SMPL_TO_BODY
    fit = fit_smpl_meshes(RegisteredFitter(model), v_smpl)[0]
    c0, q0, r0 = fit.shape[:1], fit.coordinates[:1], fit.root[:1]
    carry = _carry(model, fit.vertices[0], v_smpl @ S.T)

    rng = np.random.default_rng(seed)
    shapes = np.concatenate([c0, c0 + 0.8 * rng.standard_normal((n_population, model.n_shape))])
    with torch.no_grad():
        out = model.forward(
            shapes, np.repeat(q0, len(shapes), 0), np.repeat(r0, len(shapes), 0), dtype=torch.float64
        )
    verts = out.vertices.numpy()
    pop = _apply(model, verts, *carry) @ S  # (P, N, 3) in SMPL's frame
    pop += (v_smpl - pop[0])[None]  # the template body exactly, its shape offsets carried
    joints = smpl_joint_locations(model, out.joints.numpy()) @ S  # (P, 24, 3)

    d = (pop[1:] - pop[1:].mean(0)).reshape(n_population, -1)
    _, sv, vt = np.linalg.svd(d, full_matrices=False)
    std = sv[:n_betas] / np.sqrt(n_population - 1)
    shapedirs = (vt[:n_betas] * std[:, None]).T.reshape(len(v_smpl), 3, n_betas)

    tree = cKDTree(pop[0])
    J_reg = np.zeros((len(SMPL_JOINTS), len(v_smpl)))
    for j in range(len(SMPL_JOINTS)):
        _, near = tree.query(joints[0, j], REGRESSOR_NEIGHBOURS)
        A = np.concatenate([pop[:, near, k] for k in range(3)])  # (3P, n)
        rhs = np.concatenate([joints[:, j, k] for k in range(3)])
        A = np.vstack([A, np.full(len(near), REGRESSOR_SUM_WEIGHT)])
        w, _ = nnls(A, np.append(rhs, REGRESSOR_SUM_WEIGHT))
        J_reg[j, near] = w / max(w.sum(), 1e-9)

    ours = model.data["weights"]  # (V, n_body) in body order
    w_carried = np.einsum("nk,nkb->nb", carry[1], ours[model.faces[carry[0]]])
    names = model.skeleton.body_names
    to_joint = {name: j for j, name in enumerate(FOLLOWS) if j < 22} | SKIN
    weights = np.zeros((len(v_smpl), len(SMPL_JOINTS)))
    for k, name in enumerate(names):
        weights[:, to_joint.get(name, 0)] += w_carried[:, k]
    weights /= weights.sum(1, keepdims=True)

    parents = np.array(SMPL_PARENTS, np.int64)
    kintree = np.stack([np.where(parents < 0, 4294967295, parents), np.arange(len(parents))]).astype(
        np.uint32
    )
    arrays = {
        "v_template": v_smpl.astype(np.float32),
        "shapedirs": shapedirs.astype(np.float32),
        "posedirs": np.zeros((len(v_smpl), 3, 9 * (len(parents) - 1)), np.float32),
        "J_regressor": J_reg.astype(np.float32),
        "weights": weights.astype(np.float32),
        "kintree_table": kintree,
        "f": f_smpl.astype(np.uint32),
        "joint_names": np.array(SMPL_JOINTS),
    }
    return arrays, {"shape": c0[0], "coordinates": q0[0], "root": r0[0]}


def smpl_poses_from_ours(
    model: BodyModel, smpl: SmplModel, fitted: dict[str, np.ndarray], q: np.ndarray, root: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """SMPL poses (T, 24, 3) axis-angle and trans (T, 3) such that every SMPL joint turns as the body of
    ours it follows (:data:`FOLLOWS`) turns from its pose in the template, the elbows with the forearm's twist
    added (:func:`forearm_twist`), and the pelvis joint sits on ours.

    Args:
        fitted: our model on the template body (:func:`build_smpl_like_model`): shape, coordinates.
        q: (T, n_dof) in range; root: (T, 3).
    """
    shape = fitted["shape"]
    S = SMPL_TO_BODY
    T = len(q)
    with torch.no_grad():
        f64 = torch.float64
        rest = model.forward(shape[None], fitted["coordinates"][None], dtype=f64)
        posed = model.forward(np.repeat(shape[None], T, 0), q, root, dtype=f64)
    names = model.skeleton.body_names
    F_rest, F_t = rest.frames.numpy()[0, :, :3, :3], posed.frames.numpy()[..., :3, :3]
    body = [names.index(n) for n in FOLLOWS]
    R_rest, R_t = F_rest[body], F_t[:, body].copy()  # (24, 3, 3), (T, 24, 3, 3)
    joints = smpl_joint_locations(model, rest.joints.numpy())[0]
    for side, full in (("l", "left"), ("r", "right")):
        j, k = SMPL_JOINTS.index(f"{full}_elbow"), names.index(f"radius_{side}")
        axis = R_rest[j].T @ (joints[SMPL_JOINTS.index(f"{full}_wrist")] - joints[j])  # the ulna's frame
        R_t[:, j] = R_t[:, j] @ forearm_twist(R_rest[j], F_rest[k], R_t[:, j], F_t[:, k], axis)
    delta = S.T @ (R_t @ np.swapaxes(R_rest, -1, -2)) @ S  # global rotations in SMPL's frame
    local = delta.copy()
    for j, parent in enumerate(SMPL_PARENTS):
        if parent >= 0:
            local[:, j] = np.swapaxes(delta[:, parent], -1, -2) @ delta[:, j]
    poses = Rotation.from_matrix(local.reshape(-1, 3, 3)).as_rotvec().reshape(T, len(SMPL_JOINTS), 3)
    pelvis = smpl_joint_locations(model, posed.joints.numpy())[:, 0] @ S
    J0 = smpl.J_regressor[0] @ smpl.v_template
    return poses, pelvis - J0


def forearm_twist(
    ulna_rest: np.ndarray, radius_rest: np.ndarray, ulna: np.ndarray, radius: np.ndarray, axis: np.ndarray
) -> np.ndarray:
    """(T, 3, 3) the forearm's twist in the ulna's frame: the radius's turn against the ulna since the rest
    pose (pronation, about the radius's oblique axis) reduced to its twist about the forearm's long ``axis``
    (3,) (elbow to wrist, in the ulna's frame; the swing-twist split of the turn's quaternion).

    SMPL has one forearm segment: its elbow joint turns the whole forearm's skin, the twist included, while
    our ulna never twists and our radius pronates about an axis oblique to the forearm. An SMPL elbow that
    follows the ulna leaves the forearm's skin untwisted and every degree of pronation to the hand; one that
    follows the radius swings the wrist off the forearm's line. The ulna's turn with the radius's twist about
    the forearm's own axis keeps the forearm's line and twists its skin.

    Args:
        ulna_rest, radius_rest: (3, 3) world orientations at rest; ulna, radius: (T, 3, 3) posed.
    """
    a = axis / np.linalg.norm(axis)
    turn = np.swapaxes(ulna, -1, -2) @ radius @ (radius_rest.T @ ulna_rest)  # in the ulna's frame
    q = Rotation.from_matrix(turn).as_quat()  # (T, 4) x, y, z, w
    along = (q[:, :3] @ a)[:, None] * a
    twist = np.concatenate([along, q[:, 3:]], axis=1)
    return Rotation.from_quat(twist / np.linalg.norm(twist, axis=1, keepdims=True)).as_matrix()


def cmu_smpl_sequence(
    model: BodyModel, smpl: SmplModel, fitted: dict[str, np.ndarray], bvh: Path, frames: int | None = None
) -> dict[str, Any]:
    """An AMASS-style sequence (SMPL-H layout: poses (T, 156), zeros past the 24 body joints) of a CMU BVH
    retargeted onto our model at ``fitted`` shape; also returns our ground-truth coordinates and root."""
    motion = read_bvh(bvh, CMU_UNITS)
    with torch.no_grad():
        scales = model.forward(fitted["shape"][None]).scales.numpy()[0]
    moved = retarget(motion, model.skeleton, scales)
    q, root = moved.in_range(model.skeleton), moved.root
    if frames is not None:
        q, root = q[:frames], root[:frames]
    poses, trans = smpl_poses_from_ours(model, smpl, fitted, q, root)
    full = np.zeros((len(q), 156))
    full[:, :72] = poses.reshape(len(q), 72)
    return {
        "poses": full.astype(np.float32),
        "betas": np.zeros(16, np.float32),
        "trans": trans.astype(np.float32),
        "gender": np.array("neutral"),
        "mocap_framerate": np.array(moved.rate),
        "surface_model_type": np.array("smplh"),
        "truth_coordinates": q.astype(np.float32),
        "truth_root": root.astype(np.float32),
    }


def write_test_data(out: Path, bvh: Path, frames: int = 60) -> dict[str, Path]:
    """Write ``smpl_like_model.npz`` (the model file) and ``cmu_131_smpl.npz`` (an AMASS-style sequence
    with ``truth_coordinates`` / ``truth_root`` added) into ``out``."""
    from bodyfit.models.upgrade.smpl_model import load_smpl_model

    model = BodyModel.load()
    arrays, fitted = build_smpl_like_model(model)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"model": out / "smpl_like_model.npz", "sequence": out / "cmu_131_smpl.npz"}
    save: Any = np.savez_compressed  # keyword arrays (numpy's stub types them as its own options)
    save(paths["model"], **arrays)
    save(paths["sequence"], **cmu_smpl_sequence(model, load_smpl_model(paths["model"]), fitted, bvh, frames))
    return paths

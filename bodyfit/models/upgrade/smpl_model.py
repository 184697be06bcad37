"""SMPL-family model files (the user's own; none ships with bodyfit) and SMPL's forward pass.

A model file is an ``.npz`` or a ``.pkl`` without chumpy objects, with SMPL's keys: ``v_template``
(N, 3), ``shapedirs`` (N, 3, K), ``posedirs`` (N, 3, P) (may be zeros), ``J_regressor`` (J, N) dense or
scipy-sparse, ``weights`` (N, J), ``kintree_table`` (2, J) and ``f`` (F, 3). SMPL's frame: +Y up, the body
faces +Z, +X to the body's left; metres.

The forward pass is SMPL's linear blend skinning: shape blend, joint regression, pose blend (from the
rotation matrices minus identity, joints after the root), forward kinematics along the kinematic tree,
skinning, translation. It runs in chunks of frames so long sequences stay within memory. SMPL: M. Loper,
N. Mahmood, J. Romero, G. Pons-Moll and M. J. Black, "SMPL: A Skinned Multi-Person Linear Model", ACM
Transactions on Graphics 34(6) (SIGGRAPH Asia), 2015.
"""

from __future__ import annotations

import os
import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import sparse

from bodyfit.models.errors import BodyfitError

REQUIRED_KEYS = ("v_template", "shapedirs", "J_regressor", "weights", "kintree_table", "f")
ENV_VAR = "BODYFIT_SMPL_MODEL"


class SmplModelError(BodyfitError):
    """A missing, unreadable or malformed SMPL-family model file."""


@dataclass(frozen=True)
class SmplModel:
    """An SMPL-family model: v_template (N, 3); shapedirs (N, 3, K); posedirs (N, 3, P) or None (all
    zero); J_regressor (J, N) dense; weights (N, J); parents (J,) with -1 for the root; faces (F, 3)."""

    v_template: np.ndarray
    shapedirs: np.ndarray
    posedirs: np.ndarray | None
    J_regressor: np.ndarray
    weights: np.ndarray
    parents: np.ndarray
    faces: np.ndarray
    source: str = ""

    @property
    def n_joints(self) -> int:
        return int(self.J_regressor.shape[0])

    @property
    def n_betas(self) -> int:
        return int(self.shapedirs.shape[2])

    def forward(
        self,
        poses: np.ndarray,
        betas: np.ndarray | None = None,
        trans: np.ndarray | None = None,
        chunk: int = 256,
        at: sparse.sparray | sparse.spmatrix | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Posed meshes.

        Args:
            poses: (T, J, 3) axis-angle per joint (SMPL's 24 body joints; (T, 3 J) is accepted too).
            betas: (K',) or (T, K') shape coefficients; K' <= K are used, missing ones are 0.
            trans: (T, 3) metres.
            chunk: frames per batch (memory).
            at: optional (M, N) linear map of the vertices (a correspondence to another topology, say);
                the result is then the M mapped points, computed without the N posed vertices.
        Returns:
            vertices (T, N or M, 3) float32 and joints (T, J, 3), in SMPL's frame.
        """
        p = np.asarray(poses, np.float64)
        T = len(p)
        p = p.reshape(T, -1, 3)
        if p.shape[1] != self.n_joints:
            raise SmplModelError(f"poses have {p.shape[1]} joints but the model has {self.n_joints}")
        b = np.zeros((T, self.n_betas))
        if betas is not None:
            bb = np.atleast_2d(np.asarray(betas, np.float64))
            k = min(bb.shape[1], self.n_betas)
            b[:, :k] = bb[:, :k]
        t = np.zeros((T, 3)) if trans is None else np.asarray(trans, np.float64)
        if at is not None and at.shape[1] != len(self.v_template):
            raise SmplModelError(
                f"the map has {at.shape[1]} columns for the model's {len(self.v_template)} vertices"
            )
        vertices = np.empty((T, len(self.v_template) if at is None else at.shape[0], 3), np.float32)
        joints = np.empty((T, self.n_joints, 3), np.float32)
        for lo in range(0, T, chunk):
            hi = min(T, lo + chunk)
            vertices[lo:hi], joints[lo:hi] = self._forward(p[lo:hi], b[lo:hi], t[lo:hi], at)
        return vertices, joints

    def _forward(
        self, p: np.ndarray, b: np.ndarray, t: np.ndarray, at: sparse.sparray | sparse.spmatrix | None
    ) -> tuple[np.ndarray, np.ndarray]:
        B, N, n_j = len(p), len(self.v_template), self.n_joints
        # One shape for every frame (a sequence's betas) is shaped and regressed once.
        betas = b[:1] if (b == b[:1]).all() else b
        v_shaped = self.v_template[None] + (betas @ self.shapedirs.reshape(N * 3, -1).T).reshape(-1, N, 3)
        J = np.einsum("jn,bnk->bjk", self.J_regressor, v_shaped)  # (1 or B, J, 3)
        R = rodrigues(p)  # (B, J, 3, 3)
        rest = v_shaped[0]  # (N, 3) the first frame's shaped body; offsets from it are blended separately
        offsets = v_shaped - rest if len(v_shaped) > 1 else None  # (B, N, 3) or None
        if self.posedirs is not None:
            feat = (R[:, 1:] - np.eye(3)).reshape(B, -1)
            pose_offsets = (feat @ self.posedirs.reshape(N * 3, -1).T).reshape(B, N, 3)
            offsets = pose_offsets if offsets is None else offsets + pose_offsets
        G = np.zeros((B, n_j, 4, 4))
        for j in range(n_j):
            local = np.zeros((B, 4, 4))
            local[:, :3, :3] = R[:, j]
            parent = self.parents[j]
            local[:, :3, 3] = J[:, j] - (J[:, parent] if parent >= 0 else 0.0)
            local[:, 3, 3] = 1.0
            G[:, j] = local if parent < 0 else G[:, parent] @ local
        posed_joints = G[:, :, :3, 3] + t[:, None]
        # Transforms relative to the rest pose, A_j = G_j [I, -J_j] (+ translation), blended in float32
        # (sub-micrometre at body scale). The rest body goes through one product of per-vertex features
        # w_nj [v_n, 1] (N, 4 J) with the transforms (4 J, 3 B); offsets, where there are any, through the
        # blended rotations. A map ``at`` is applied to the features and offsets (it is linear).
        A = G[:, :, :3, :].copy()
        A[:, :, :, 3] -= (G[:, :, :3, :3] @ J[..., None])[..., 0]
        A[:, :, :, 3] += t[:, None]
        A32 = A.astype(np.float32)
        weights = self.weights.astype(np.float32)
        rest_h = np.concatenate([rest, np.ones((N, 1))], axis=1).astype(np.float32)
        features = (weights[:, :, None] * rest_h[:, None, :]).reshape(N, n_j * 4)
        if at is not None:
            features = np.asarray(at @ features, np.float32)
        transforms = A32.transpose(1, 3, 0, 2).reshape(n_j * 4, B * 3)  # [j k, b i] = A[b, j, i, k]
        verts = (features @ transforms).reshape(-1, B, 3)
        if offsets is not None:
            rotations = (weights @ A32[..., :3].transpose(1, 0, 2, 3).reshape(n_j, B * 9)).reshape(N, B, 3, 3)
            moved = np.einsum("nbij,nbj->nbi", rotations, np.moveaxis(offsets, 0, 1).astype(np.float32))
            verts += moved if at is None else np.asarray(at @ moved.reshape(N, B * 3)).reshape(-1, B, 3)
        return np.moveaxis(verts, 0, 1), posed_joints


def rodrigues(axis_angle: np.ndarray) -> np.ndarray:
    """(..., 3) axis-angle -> (..., 3, 3) rotation matrices.

    Rodrigues' formula (O. Rodrigues, "Des lois géométriques qui régissent les déplacements d'un système
    solide dans l'espace", Journal de Mathématiques Pures et Appliquées 5, 1840).
    """
    a = np.asarray(axis_angle, np.float64)
    theta = np.linalg.norm(a, axis=-1, keepdims=True)
    k = a / np.maximum(theta, 1e-12)
    K = np.zeros((*a.shape[:-1], 3, 3))
    K[..., 0, 1], K[..., 0, 2] = -k[..., 2], k[..., 1]
    K[..., 1, 0], K[..., 1, 2] = k[..., 2], -k[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -k[..., 1], k[..., 0]
    s, c = np.sin(theta)[..., None], np.cos(theta)[..., None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def model_path(path: str | os.PathLike[str] | None) -> Path:
    """The model file: ``path``, else $BODYFIT_SMPL_MODEL; an error saying how to give one otherwise."""
    chosen = path or os.environ.get(ENV_VAR)
    if not chosen:
        raise SmplModelError(
            f"no SMPL-family model file given: pass its path (--smpl-model) or set {ENV_VAR}"
        )
    p = Path(chosen)
    if not p.is_file():
        raise SmplModelError(f"SMPL model file {p} does not exist")
    return p


def load_smpl_model(path: str | os.PathLike[str] | None = None) -> SmplModel:
    """Read an SMPL-family model file (.npz, or .pkl without chumpy).

    Raises:
        SmplModelError: missing file, chumpy pickle, missing keys, inconsistent shapes.
    """
    p = model_path(path)
    data = _read(p)
    missing = [k for k in REQUIRED_KEYS if k not in data]
    if missing:
        raise SmplModelError(
            f"{p.name} lacks {', '.join(missing)}; an SMPL-family model file needs "
            f"{', '.join(REQUIRED_KEYS)} "
            f"(found {', '.join(sorted(data)) or 'nothing'})"
        )
    return _model(data, str(p))


def _read(p: Path) -> dict[str, Any]:
    if p.suffix == ".npz":
        try:
            with np.load(p, allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        except (OSError, ValueError, zipfile.BadZipFile) as exc:
            raise SmplModelError(f"cannot read {p.name} as .npz: {exc}") from None
    if p.suffix == ".pkl":
        try:
            with p.open("rb") as f:
                data = pickle.load(f, encoding="latin1")
        except ModuleNotFoundError as exc:
            raise SmplModelError(
                f"{p.name} holds {exc.name} objects (an original SMPL pickle with chumpy arrays); convert it "
                "once to plain numpy (e.g. load it where chumpy is installed and np.savez the arrays) and "
                "pass the .npz"
            ) from None
        except Exception as exc:
            raise SmplModelError(f"cannot read {p.name} as a pickle: {exc}") from None
        if not isinstance(data, dict):
            raise SmplModelError(f"{p.name} holds a {type(data).__name__}, not a dictionary of arrays")
        return data
    raise SmplModelError(f"{p.name}: SMPL model files are .npz or .pkl")


def _dense(a: Any) -> np.ndarray:
    return np.asarray(a.toarray() if hasattr(a, "toarray") else a, np.float64)


def _shape_problems(
    v: np.ndarray,
    shapedirs: np.ndarray,
    J_reg: np.ndarray,
    weights: np.ndarray,
    kintree: np.ndarray,
    faces: np.ndarray,
    posedirs: np.ndarray | None,
) -> list[str]:
    """What is wrong with the arrays' shapes (N vertices from ``v``, J joints from ``J_reg``); empty if
    nothing is."""
    N, J = len(v), len(J_reg)
    problems = []
    if v.ndim != 2 or v.shape[1] != 3:
        problems.append(f"v_template must be (N, 3), got {v.shape}")
    if shapedirs.ndim != 3 or shapedirs.shape[:2] != (N, 3):
        problems.append(f"shapedirs must be ({N}, 3, K), got {shapedirs.shape}")
    if J_reg.shape != (J, N):
        problems.append(f"J_regressor must be (J, {N}), got {J_reg.shape}")
    if weights.shape != (N, J):
        problems.append(f"weights must be ({N}, {J}), got {weights.shape}")
    if kintree.shape != (2, J):
        problems.append(f"kintree_table must be (2, {J}), got {kintree.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or (faces.size and faces.max() >= N):
        problems.append(f"f must be (F, 3) indices below {N}")
    if posedirs is not None and (
        posedirs.ndim != 3 or posedirs.shape[:2] != (N, 3) or posedirs.shape[2] != 9 * (J - 1)
    ):
        problems.append(f"posedirs must be ({N}, 3, {9 * (J - 1)}), got {posedirs.shape}")
    return problems


def _model(data: dict[str, Any], source: str) -> SmplModel:
    v = _dense(data["v_template"])
    shapedirs = _dense(data["shapedirs"])
    J_reg = _dense(data["J_regressor"])
    weights = _dense(data["weights"])
    kintree = np.asarray(data["kintree_table"]).astype(np.int64)
    faces = np.asarray(data["f"]).astype(np.int64)
    posedirs = _dense(data["posedirs"]) if "posedirs" in data else None
    J = len(J_reg)
    problems = _shape_problems(v, shapedirs, J_reg, weights, kintree, faces, posedirs)
    if problems:
        raise SmplModelError(f"{Path(source).name} is malformed: " + "; ".join(problems))
    parents = kintree[0].copy()
    parents[0] = -1
    if np.any(parents[1:] >= np.arange(1, J)) or np.any(parents[1:] < 0):
        raise SmplModelError(f"{Path(source).name}: kintree_table must list each joint's parent before it")
    if posedirs is not None and not np.any(posedirs):
        posedirs = None
    return SmplModel(v, shapedirs, posedirs, J_reg, weights, parents, faces, source)

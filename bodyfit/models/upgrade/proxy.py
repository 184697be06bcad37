"""Path (b)'s proxy: an SMPL-format body in our topology, built at asset time from anny's SOMA rig.

anny's ``soma`` rig (NVIDIA SOMA-X's skeleton on anny's mesh) is in SMPL's frame (+Y up, facing +Z, +X to
the body's left) with a T-pose reference and rotations relative to it in world-aligned axes, SMPL's
conventions. Its skin, restricted to our template's vertices (the same mesh), is posed in that T-pose and
written as an SMPL-format model (asset ``smpl_proxy.npz``, SMPL's key names):

* ``v_template``: the T-posed body at the adult population's mean phenotype;
* ``shapedirs``: the T-posed bodies' change with :func:`phenotype_features` of anny's sliders (gender, age,
  muscle, weight, height, proportions, and their products), least squares over a sampled adult
  population, so the proxy's betas are those features' offsets from the mean's (``phenotype_names``,
  ``phenotype_mean``);
* ``J_regressor``: non-negative, fitted to the SOMA joints mapped onto SMPL's 24 (:data:`SOMA_FOR_SMPL`);
* ``weights``: SOMA's skinning weights summed onto those joints; no pose correctives.

Posed by SMPL joint rotations (the SMPL forward pass of :mod:`~bodyfit.models.upgrade.smpl_model`), it gives
meshes in our own topology, which our model then fits as a registered sequence. Shape comes from hints
(:class:`ShapeHints`: sex, stature, mass) solved on the proxy's phenotype sliders, else the mean. Building
needs anny (extra ``build``); using the asset does not. SMPL's format and forward pass: M. Loper, N. Mahmood,
J. Romero, G. Pons-Moll and M. J. Black, "SMPL: A Skinned Multi-Person Linear Model", ACM Transactions on
Graphics 34(6) (SIGGRAPH Asia), 2015.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bodyfit.models.errors import BodyfitError
from bodyfit.models.upgrade.rest_pose import rest_alignment, rest_rotations_deg, segment_alignment
from bodyfit.models.upgrade.smpl_joints import SMPL_JOINTS, SMPL_PARENTS
from bodyfit.models.upgrade.smpl_model import SmplModel, load_smpl_model

PROXY_ASSET = "smpl_proxy.npz"
BODY_DENSITY = 985.0  # kg/m^3, whole body with the lungs: mass = density x the closed skin's volume
# SMPL's 24 joints and the SOMA bones each stands for (its skin follows the first; the rest add their skin).
SOMA_FOR_SMPL: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("pelvis", ("Hips", "Root")),
    ("left_hip", ("LeftLeg",)),
    ("right_hip", ("RightLeg",)),
    ("spine1", ("Spine1",)),
    ("left_knee", ("LeftShin",)),
    ("right_knee", ("RightShin",)),
    ("spine2", ("Spine2",)),
    ("left_ankle", ("LeftFoot",)),
    ("right_ankle", ("RightFoot",)),
    ("spine3", ("Chest",)),
    ("left_foot", ("LeftToeBase", "LeftToeEnd")),
    ("right_foot", ("RightToeBase", "RightToeEnd")),
    ("neck", ("Neck1", "Neck2")),
    ("left_collar", ("LeftShoulder",)),
    ("right_collar", ("RightShoulder",)),
    ("head", ("Head", "HeadEnd", "Jaw", "LeftEye", "RightEye")),
    ("left_shoulder", ("LeftArm",)),
    ("right_shoulder", ("RightArm",)),
    ("left_elbow", ("LeftForeArm",)),
    ("right_elbow", ("RightForeArm",)),
    ("left_wrist", ("LeftHand",)),
    ("right_wrist", ("RightHand",)),
    ("left_hand", ("LeftHandMiddle1", "LeftHand*")),  # the fingers
    ("right_hand", ("RightHandMiddle1", "RightHand*")),
)
SEX_GENDER = {"male": 0.0, "female": 1.0, "neutral": 0.5}  # anny's gender slider
SHOULDER_ALONG_ARM = 0.25
"""Where the proxy's shoulder joints sit: this fraction of the way from SOMA's arm bone head to its forearm
bone head. SMPL's shoulder joint is the glenohumeral centre (our anatomical shoulder joint on the CC BY man
lies 65 mm lateral of SOMA's arm head, a quarter of the 263 mm bone); SOMA's arm bone starts at the
shoulder's medial end. Turned about that medial point, an arm brought down from SMPL's rest pose sinks
5-7 cm lower than SMPL's, and the fit holds the scapula at its lowest to follow it."""


class ShapeHintError(BodyfitError):
    """Hints that cannot describe a person (unknown sex, implausible sizes); ``field`` names the hint."""

    def __init__(self, message: str, field: str) -> None:
        super().__init__(message)
        self.field = field


@dataclass(frozen=True)
class ShapeHints:
    """What is known of the subject when betas cannot be used: sex ("male", "female", "neutral"), stature
    (m, standing, heel to vertex) and mass (kg); None where unknown."""

    sex: str | None = None
    height_m: float | None = None
    mass_kg: float | None = None

    def __post_init__(self) -> None:
        if self.sex is not None and self.sex not in SEX_GENDER:
            raise ShapeHintError(f"sex must be one of {', '.join(SEX_GENDER)}; got {self.sex!r}", "sex")
        for name, value, lo, hi in (
            ("height_m", self.height_m, 1.2, 2.3),
            ("mass_kg", self.mass_kg, 30, 200),
        ):
            if value is not None and not (np.isfinite(value) and lo <= value <= hi):
                raise ShapeHintError(
                    f"{name} must be an adult's, between {lo} and {hi}; got {value} (metres and kilograms)",
                    name,
                )

    @classmethod
    def given(cls, sex: str | None, height_m: float | None, mass_kg: float | None) -> ShapeHints | None:
        """The hints from optional fields (an empty sex counts as none given); None when none is given.

        Raises:
            ShapeHintError: naming the hint that cannot describe an adult.
        """
        if not sex and height_m is None and mass_kg is None:
            return None
        return cls(sex or None, height_m, mass_kg)


@dataclass(frozen=True)
class SmplProxy:
    """The loaded proxy: an SMPL-format model in our topology whose betas are
    :func:`phenotype_features` of anny's sliders (``phenotype_names``, each in [0, 1]) minus those of the
    population mean (``phenotype_mean``)."""

    model: SmplModel
    phenotype_names: tuple[str, ...]
    phenotype_mean: np.ndarray

    def betas(self, phenotype: np.ndarray) -> np.ndarray:
        """(n_betas,) the proxy's betas for phenotype (K,)."""
        return (phenotype_features(phenotype[None]) - phenotype_features(self.phenotype_mean[None]))[0]

    def body(self, phenotype: np.ndarray) -> np.ndarray:
        """The T-posed body (N, 3) of phenotype (K,)."""
        return self.model.v_template + self.model.shapedirs @ self.betas(phenotype)

    def stature(self, phenotype: np.ndarray) -> float:
        """Heel-to-vertex height (m) of the T-posed body."""
        y = self.body(phenotype)[:, 1]
        return float(y.max() - y.min())

    def mass(self, phenotype: np.ndarray) -> float:
        """Mass (kg): the closed skin's volume times :data:`BODY_DENSITY`."""
        v = self.body(phenotype)
        a, b, c = (v[self.model.faces[:, k]] for k in range(3))
        return float(abs(np.einsum("fi,fi->f", a, np.cross(b, c)).sum()) / 6.0 * BODY_DENSITY)

    def phenotype(self, hints: ShapeHints | None, gender: str | None = None) -> tuple[np.ndarray, list[str]]:
        """The phenotype (K,) for the hints (the sequence's own ``gender`` when no sex is hinted; else the
        population mean), and notes that say what the shape came from. Stature and mass are met on the height
        and weight sliders by Gauss-Newton steps; a hint beyond the sliders' range is met as far as they go,
        and the notes say so."""
        hints = hints or ShapeHints()
        sex = hints.sex or (gender if gender in SEX_GENDER else None)
        sex_source = "" if hints.sex or sex is None else " (the sequence's gender)"
        names = list(self.phenotype_names)
        p = self.phenotype_mean.copy()
        if sex is not None:
            p[names.index("gender")] = SEX_GENDER[sex]
        wanted = ((self.stature, "height", hints.height_m), (self.mass, "weight", hints.mass_kg))
        goals = [(f, names.index(slider), v) for f, slider, v in wanted if v is not None]
        free = [k for _, k, _ in goals]
        notes = []
        for _ in range(10 if goals else 0):
            r = np.array([f(p) - v for f, _, v in goals])
            J = np.empty((len(goals), len(free)))
            for j, k in enumerate(free):
                step = np.zeros_like(p)
                step[k] = 1e-3
                J[:, j] = [(f(p + step) - f(p)) / 1e-3 for f, _, _ in goals]
            p[free] = np.clip(p[free] - np.linalg.lstsq(J, r, rcond=None)[0], 0.0, 1.0)
        for f, _, v in goals:
            if abs(f(p) - v) > 0.01 * v:
                notes.append(f"a shape hint of {v:g} could be met only to {f(p):.3g} by the proxy's sliders")
        given = [f"sex {sex}{sex_source}"] if sex else []
        sizes = (("height", hints.height_m, "m"), ("mass", hints.mass_kg, "kg"))
        given += [f"{k} {v:g} {unit}" for k, v, unit in sizes if v is not None]
        shape = "shape from hints: " + ", ".join(given) if given else "shape: the adult population mean"
        notes.insert(0, f"{shape} (stature {self.stature(p):.2f} m, mass {self.mass(p):.0f} kg)")
        return p, notes


def load_proxy(folder: Path | None = None) -> SmplProxy:
    """The stored proxy (asset :data:`PROXY_ASSET`, hash-checked)."""
    from bodyfit.models.assets import verified_asset

    path = verified_asset(PROXY_ASSET, folder)
    with np.load(path) as d:
        names = tuple(str(n) for n in d["phenotype_names"])
        mean = np.asarray(d["phenotype_mean"], np.float64)
    return SmplProxy(load_smpl_model(path), names, mean)


def phenotype_features(p: np.ndarray) -> np.ndarray:
    """The proxy's shape features of phenotypes p (n, K): the sliders and their pairwise products and squares
    (n, K + K (K + 1) / 2); anny's body is multilinear in its sliders, so these carry most of it."""
    i, j = np.triu_indices(p.shape[1])
    return np.concatenate([p, p[:, i] * p[:, j]], axis=1)


# -- asset build (needs anny) ------------------------------------------------------------------------------
def _smpl_columns(labels: list[str]) -> np.ndarray:
    """(n_soma,) the SMPL joint each SOMA bone's skin goes to (a trailing ``*`` in the table matches a
    prefix, after the exact names)."""
    column = -np.ones(len(labels), np.int64)
    for exact in (True, False):
        for j, (_, bones) in enumerate(SOMA_FOR_SMPL):
            for pattern in bones:
                for i, label in enumerate(labels):
                    hit = (
                        label == pattern
                        if exact
                        else pattern.endswith("*") and label.startswith(pattern[:-1])
                    )
                    if hit and column[i] < 0:
                        column[i] = j
    if (column < 0).any():
        raise AssertionError(
            f"SOMA bones without an SMPL joint: {[labels[i] for i in np.flatnonzero(column < 0)]}"
        )
    return column


def _sample_adults(anny: Any, soma: Any, names: tuple[str, ...], count: int, seed: int) -> np.ndarray:
    """(count, K) phenotypes (``names`` order) of adults aged 18 to 90 from anny's shape distribution."""
    import torch

    from bodyfit.models.body.anny_source import seeded

    dist = anny.shape_distribution.SimpleShapeDistribution(
        soma,
        morphological_age_distribution=torch.distributions.Uniform(
            torch.tensor(18.0, dtype=torch.float64), torch.tensor(90.0, dtype=torch.float64)
        ),
    )
    with seeded(seed):
        _, pheno = dist.sample(count)
    return np.stack([pheno[n].numpy() for n in names], 1)


def _t_posed(
    soma: Any, names: tuple[str, ...], pose: np.ndarray, keep: np.ndarray, p: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Bodies (n, V, 3) and SOMA bone heads (n, 78, 3) for phenotypes p (n, K), each bone turned by ``pose``
    (78, 4, 4) from the T-pose (relative to its parent in world-aligned axes: local-ref, the rig's)."""
    import torch

    kwargs = {n: torch.as_tensor(p[:, k]) for k, n in enumerate(names)}
    bones = torch.as_tensor(pose, dtype=torch.float64).expand(len(p), *pose.shape)
    with torch.no_grad():
        out = soma(pose_parameters=bones, phenotype_kwargs=kwargs)
    return out["vertices"][:, keep].numpy(), out["bone_poses"][..., :3, 3].numpy()


def _shape_directions(
    t_posed: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    V: np.ndarray,
    v_mean: np.ndarray,
    P: np.ndarray,
    P_test: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares shape directions (n_features, V * 3) of the bodies V (n, V, 3) of phenotypes P (n, K)
    about v_mean (1, V, 3), and their per-vertex error (n_test, V) in metres on the phenotypes P_test."""
    mean = P.mean(0)
    D = phenotype_features(P) - phenotype_features(mean[None])
    flat = V.reshape(len(V), -1) - v_mean.reshape(1, -1)
    dirs, *_ = np.linalg.lstsq(D, flat, rcond=None)
    V_test, _ = t_posed(P_test)
    D_test = phenotype_features(P_test) - phenotype_features(mean[None])
    gap = np.linalg.norm(v_mean + (D_test @ dirs).reshape(V_test.shape) - V_test, axis=-1)
    return dirs, gap


def _smpl_weights(soma: Any, keep: np.ndarray, labels: list[str]) -> np.ndarray:
    """(V, 24) SOMA's skinning weights of the kept vertices summed onto SMPL's joints, rows summing to 1."""
    w = soma.vertex_bone_weights.numpy()[keep]
    idx = soma.vertex_bone_indices.numpy()[keep]
    weights = np.zeros((len(keep), len(SMPL_JOINTS)))
    cols = _smpl_columns(labels)
    np.add.at(weights, (np.repeat(np.arange(len(keep)), w.shape[1]), cols[idx].ravel()), w.ravel())
    weights /= weights.sum(1, keepdims=True)
    return weights


def shoulder_pivots(heads: np.ndarray, labels: list[str], joints: np.ndarray) -> np.ndarray:
    """SMPL's joints (n, 24, 3) read off the SOMA bone heads (n, n_soma, 3), with each shoulder moved
    :data:`SHOULDER_ALONG_ARM` of the way down the SOMA arm bone (``labels`` names the heads)."""
    out = joints.copy()
    for side in ("left", "right"):
        arm, forearm = (heads[:, labels.index(f"{side.title()}{bone}")] for bone in ("Arm", "ForeArm"))
        out[:, SMPL_JOINTS.index(f"{side}_shoulder")] = arm + SHOULDER_ALONG_ARM * (forearm - arm)
    return out


def build_proxy(
    cache_dir: Path,
    faces: np.ndarray,
    n_bodies: int = 400,
    seed: int = 11,
    held_out: int = 50,
    smpl_rest: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The proxy's arrays (SMPL keys plus ``phenotype_names``, ``phenotype_mean``) and build metrics.

    Args:
        cache_dir: anny's and warp's caches; faces: (F, 3) our template's triangles (checked against the
            SOMA model's mesh); n_bodies: sampled adults for the shape directions and the regressor;
            held_out: more adults, only to measure the shape directions.
        smpl_rest: bodies in SMPL's rest pose (K, V, 3), carried onto our topology in SMPL's frame, and their
            usable vertices (K, V) bool: the proxy is turned into their pose
            (:mod:`bodyfit.models.upgrade.rest_pose`); None keeps SOMA's T-pose.
    """
    os.environ.setdefault("ANNY_CACHE_DIR", str(cache_dir / "anny"))
    os.environ.setdefault("WARP_CACHE_PATH", str(cache_dir / "warp"))
    import anny  # build-time dependency (extra "build")
    import torch

    from bodyfit.models.body.anny_source import largest_component
    from bodyfit.models.body.shape_space import fit_joint_regressor

    soma = anny.Anny(rig="soma", pose_parameterization="local-ref").to(torch.float64)
    keep, soma_faces = largest_component(soma.faces.numpy().astype(np.int64), soma.template_vertices.shape[0])
    if not np.array_equal(soma_faces, faces):
        raise AssertionError("anny's SOMA-rig mesh is not our template's mesh")
    labels = list(soma.bone_labels)
    head_bone = [labels.index(bones[0]) for _, bones in SOMA_FOR_SMPL]
    names = tuple(str(n) for n in soma.phenotype_labels)
    P_all = _sample_adults(anny, soma, names, n_bodies + held_out, seed)  # (N, K)
    P, P_test = P_all[:n_bodies], P_all[n_bodies:]
    mean = P.mean(0)

    weights = _smpl_weights(soma, keep, labels)
    pose = np.repeat(np.eye(4)[None], len(labels), axis=0)
    alignment = np.repeat(np.eye(3)[None], len(SMPL_JOINTS), axis=0)
    if smpl_rest is not None:
        t_mean, t_heads = _t_posed(soma, names, pose, keep, mean[None])
        segments = segment_alignment(t_mean[0], smpl_rest[0], weights, t_heads[0, head_bone], smpl_rest[1])
        alignment = rest_alignment(segments)
    pose[head_bone, :3, :3] = alignment  # SMPL's rest pose: each SMPL joint's bone turned into it

    def t_posed(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return _t_posed(soma, names, pose, keep, p)

    verts, heads = zip(*(t_posed(P[i : i + 50]) for i in range(0, len(P), 50)), strict=True)
    V, H = np.concatenate(verts), np.concatenate(heads)
    v_mean, _ = t_posed(mean[None])
    dirs, gap = _shape_directions(t_posed, V, v_mean, P, P_test)  # (n_features, V * 3), (n_test, V)
    joints = shoulder_pivots(H, labels, H[:, head_bone])
    regressor = fit_joint_regressor(V, joints)

    arrays = {
        "v_template": v_mean[0],
        "shapedirs": dirs.T.reshape(len(keep), 3, len(dirs)),
        "J_regressor": regressor,
        "weights": weights,
        "kintree_table": np.array([SMPL_PARENTS, np.arange(len(SMPL_JOINTS))], np.int64),
        "f": faces.astype(np.int64),
        "phenotype_names": np.array(names),
        "phenotype_mean": mean,
    }
    metrics = {
        "bodies": n_bodies,
        "shape_held_out_mean_mm": round(float(gap.mean()) * 1000, 3),
        "shape_held_out_max_mm": round(float(gap.max()) * 1000, 2),
        "joint_regressor_mean_mm": round(
            float(np.linalg.norm(np.einsum("jv,nvc->njc", regressor, V) - joints, axis=-1).mean()) * 1000, 3
        ),
        "phenotypes": list(names),
        "anny": getattr(anny, "__version__", "unknown"),
        "rest_pose_deg": rest_rotations_deg(alignment),
    }
    return arrays, metrics

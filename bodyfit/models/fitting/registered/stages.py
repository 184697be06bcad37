"""What a registered fit's stages fit: the typed :class:`Stage` and :class:`RegisteredFitConfig`, the default
stage table, and the vertex sets, coordinate masks and shape masks that a stage's names select.

The staging follows BLSM's fitting (Wang, Güler, Kokkinos, Papandreou, Zafeiriou, "BLSM: A Bone-Level
Skinned Model of the Human Mesh", ECCV 2020, section 5.2): the trunk first, then the limbs, then everything
on all the vertices, so that the limbs' many local minima are met with the trunk already in place.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass
from numbers import Real
from typing import Literal, get_args

import numpy as np
import torch
from scipy.spatial import cKDTree

from bodyfit.models.body.model import BodyModel
from bodyfit.models.skeleton.model import Skeleton

TRUNK_BODIES = ("pelvis", "torso", "thoracic_link", "thorax")
TRUNK_DOF_PREFIXES = ("pelvis_", "lumbar_", "thorax_")
# The trunk and the legs' flexion: a seated or crouching body's pose, which the trunk alone can only mimic
# by bending the spine.
CORE_DOF_PREFIXES = (*TRUNK_DOF_PREFIXES, "hip_flexion_", "knee_angle_")
# A head-and-shoulders capture: the mean body's vertices this far below the top of its head (head, neck,
# shoulders and upper chest), and the DOFs that place them (the trunk's, the neck's and the scapulae's).
UPPER_BODY_M = 0.55
UPPER_DOF_PREFIXES = (*TRUNK_DOF_PREFIXES, "neck_", "scapula_")
MIN_PART_WEIGHT = 0.7  # a vertex belongs to a body's rigid part above this skinning weight
MIN_PART_VERTICES = 20

CoordinateSet = Literal["trunk", "core", "upper", "all"]
"""The coordinates a stage frees: the trunk's (pelvis, lumbar, thoracic DOFs), the core's (those and the
hips' and knees' flexion), the upper body's (the trunk's, the neck's and the scapulae's) or all."""
ShapeSet = Literal["none", "bone", "all"]
"""The shape coefficients a stage frees: none, the bone-length ones, or all (bone lengths and identity)."""
VertexSet = Literal["trunk", "coarse", "subset", "dense", "upper", "all"]
"""The vertices a stage fits: the trunk bodies' skin; nested farthest-point subsets of the whole body
("coarse" in "subset" in "dense", sizes in :class:`RegisteredFitConfig`); the head and shoulders
(:data:`UPPER_BODY_M`); or all."""
COORDINATE_SETS: tuple[str, ...] = get_args(CoordinateSet)
SHAPE_SETS: tuple[str, ...] = get_args(ShapeSet)
VERTEX_SETS: tuple[str, ...] = get_args(VertexSet)


def check_choice(owner: str, field: str, value: object, allowed: Collection[object]) -> None:
    """Raise a ValueError naming ``owner.field``, the bad value and the allowed ones unless value is one of
    ``allowed``: a typo in a config fails where the config is built, not deep inside a fit."""
    if value not in allowed:
        choices = ", ".join(repr(a) for a in allowed)
        raise ValueError(f"{owner}.{field} must be one of {choices}; got {value!r}")


def check_at_least(owner: str, field: str, value: object, least: float) -> None:
    """Raise a ValueError naming ``owner.field`` and the bad value unless value is a number >= least."""
    if isinstance(value, bool) or not isinstance(value, Real) or not float(value) >= least:
        raise ValueError(f"{owner}.{field} must be at least {least}; got {value!r}")


@dataclass(frozen=True, kw_only=True)
class Stage:
    """One fitting stage: ``iterations`` L-BFGS iterations over the coordinates ``coordinates`` (a
    :data:`CoordinateSet`), the root and the shape coefficients ``shape`` (a :data:`ShapeSet`), fitting the
    vertex set ``vertices`` (a :data:`VertexSet`). metric: None, or the vertex set whose Gauss-Newton metric
    (:meth:`.fitter.RegisteredFitter.metric`, at the stage's start) the stage's L-BFGS runs in.

    Raises:
        ValueError: a field outside its choices (the message names the field and the allowed values), or
            fewer than one iteration.
    """

    name: str
    coordinates: CoordinateSet
    shape: ShapeSet
    vertices: VertexSet
    iterations: int
    metric: VertexSet | None = None

    def __post_init__(self) -> None:
        check_choice("Stage", "coordinates", self.coordinates, COORDINATE_SETS)
        check_choice("Stage", "shape", self.shape, SHAPE_SETS)
        check_choice("Stage", "vertices", self.vertices, VERTEX_SETS)
        if self.metric is not None:
            check_choice("Stage", "metric", self.metric, VERTEX_SETS)
        check_at_least("Stage", "iterations", self.iterations, 1)


# The last two stages run in the Gauss-Newton metric of the 200-vertex subset: on the 200 held-out bodies of
# benchmarks/fit_registered.py, 25 + 5 iterations so gave 1.50 mm at 40 ms per mesh against 1.83 mm at 45 ms
# for 80 + 10 plain ones (the 1,000-vertex subset's metric costs more than the iterations it saves).
DEFAULT_STAGES = (
    Stage(name="trunk", coordinates="trunk", shape="bone", vertices="trunk", iterations=10),
    Stage(name="limbs", coordinates="all", shape="none", vertices="subset", iterations=20),
    Stage(name="all", coordinates="all", shape="all", vertices="subset", iterations=25, metric="coarse"),
    Stage(name="refine", coordinates="all", shape="all", vertices="all", iterations=5, metric="coarse"),
)
# The damping of the stages' metrics (``regularise`` of :meth:`.fitter.RegisteredFitter.metric`): at 1e-3 the
# first (Newton) step took one of six bodies of the model, turned anywhere, into a wrong minimum (3.6 mm
# against 0.6 mm without the metric); at 3e-3 all six end within 0.4 mm.
STAGE_METRIC_DAMPING = 3e-3
DTYPES = (torch.float32, torch.float64)


@dataclass(frozen=True, kw_only=True)
class RegisteredFitConfig:
    """stages: run in order; dense_size, subset_size, coarse_size: vertices of the farthest-point subsets
    "dense", "subset" and "coarse" (the first ones of the same sample); shape_prior: weight of
    |c|^2 (coefficients are in population standard deviations) against the loss in mm^2; dtype: the
    optimisation's float type (torch.float32 or torch.float64).

    Raises:
        ValueError: no stages, a subset of fewer than one vertex, a negative prior or another dtype.
    """

    stages: tuple[Stage, ...] = DEFAULT_STAGES
    dense_size: int = 6500
    subset_size: int = 1000
    coarse_size: int = 200
    shape_prior: float = 1e-2
    dtype: torch.dtype = torch.float32

    def __post_init__(self) -> None:
        check_at_least("RegisteredFitConfig", "len(stages)", len(self.stages), 1)
        for name in ("dense_size", "subset_size", "coarse_size"):
            check_at_least("RegisteredFitConfig", name, getattr(self, name), 1)
        check_at_least("RegisteredFitConfig", "shape_prior", self.shape_prior, 0.0)
        check_choice("RegisteredFitConfig", "dtype", self.dtype, DTYPES)


def farthest_point_subset(points: np.ndarray, n: int) -> np.ndarray:
    """Indices (n,) of a farthest-point sample of points (V, 3), starting from the point nearest the mean
    (Eldar, Lindenbaum, Porat, Zeevi, "The Farthest Point Strategy for Progressive Image Sampling", IEEE
    Transactions on Image Processing, 1997). Each pick lowers the distances of the points within the current
    largest distance of it only (a ball query), 10x faster than updating all at 5,000 of 13,000 vertices,
    with the same picks."""
    n = min(n, len(points))
    chosen = np.empty(n, np.int64)
    chosen[0] = int(np.argmin(np.linalg.norm(points - points.mean(0), axis=1)))
    dist = np.linalg.norm(points - points[chosen[0]], axis=1)
    tree = cKDTree(points)
    for k in range(1, n):
        c = chosen[k] = int(np.argmax(dist))
        near = np.asarray(tree.query_ball_point(points[c], dist[c]), np.int64)
        dist[near] = np.minimum(dist[near], np.linalg.norm(points[near] - points[c], axis=1))
    return chosen


def vertex_sets(model: BodyModel, config: RegisteredFitConfig) -> dict[str, np.ndarray]:
    """Each :data:`VertexSet`'s sorted vertex indices (V_set,) into the model's template."""
    template = model.data["vertices_mean"]
    body_of_vertex = model.vertex_bodies
    trunk_ids = [model.skeleton.body_names.index(b) for b in TRUNK_BODIES]
    cfg = config
    spread = farthest_point_subset(template, max(cfg.dense_size, cfg.subset_size, cfg.coarse_size))
    return {
        "trunk": np.flatnonzero(np.isin(body_of_vertex, trunk_ids)),
        "dense": np.sort(spread[: cfg.dense_size]),
        "subset": np.sort(spread[: cfg.subset_size]),
        "coarse": np.sort(spread[: cfg.coarse_size]),
        "upper": np.flatnonzero(template[:, 1] > template[:, 1].max() - UPPER_BODY_M),
        "all": np.arange(model.n_vertices),
    }


def coordinate_masks(skeleton: Skeleton, dtype: torch.dtype) -> dict[str, torch.Tensor]:
    """Each :data:`CoordinateSet`'s mask (n_dof,) over the skeleton's coordinates, 1 where free."""
    masks = {
        name: torch.as_tensor([n.startswith(prefixes) for n in skeleton.dof_names], dtype=dtype)
        for name, prefixes in (
            ("trunk", TRUNK_DOF_PREFIXES),
            ("core", CORE_DOF_PREFIXES),
            ("upper", UPPER_DOF_PREFIXES),
        )
    }
    masks["all"] = torch.ones(skeleton.n_dof, dtype=dtype)
    return masks


def shape_masks(n_shape: int, n_bone: int, dtype: torch.dtype) -> dict[str, torch.Tensor]:
    """Each :data:`ShapeSet`'s mask (n_shape,) over the shape coefficients (the first ``n_bone`` are the
    bone-length ones), 1 where free."""
    return {
        "none": torch.zeros(n_shape, dtype=dtype),
        "bone": torch.as_tensor(np.arange(n_shape) < n_bone, dtype=dtype),
        "all": torch.ones(n_shape, dtype=dtype),
    }


def rigid_parts(weights: np.ndarray) -> tuple[list[int], list[np.ndarray]]:
    """The bodies with enough skin of their own for a rigid fit, and those vertices: skinning weights
    (V, n_body) give the bodies (k,) with at least :data:`MIN_PART_VERTICES` vertices weighted above
    :data:`MIN_PART_WEIGHT`, and each one's vertex indices."""
    bodies: list[int] = []
    index: list[np.ndarray] = []
    for j in range(weights.shape[1]):
        own = np.flatnonzero(weights[:, j] > MIN_PART_WEIGHT)
        if len(own) >= MIN_PART_VERTICES:
            bodies.append(j)
            index.append(own)
    return bodies, index

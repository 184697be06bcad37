"""Virtual markers on our template and subject calibration: segment scales and marker placement.

Scales follow the body model's bone shape space with a per-segment correction,
``s = (s_mean + c P_b) * exp(r)`` (``c`` the bone coefficients, standard normal prior; ``r`` a log
correction per segment and axis, left and right tied, prior sigma :data:`SCALE_SIGMA`), so segments no
marker sees still get plausible lengths from the ones that are seen (eq. 4 of H. Wang, R. A. Güler, I.
Kokkinos, G. Papandreou and S. Zafeiriou, "BLSM: A Bone-Level Skinned Model of the Human Mesh", ECCV 2020).

The solvers that use these pieces are in :mod:`.subject` (calibration) and :mod:`.marker_solve` (IK).
"""

from __future__ import annotations

import copy
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace

import numpy as np
import torch

from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common.surface import vertex_normals
from bodyfit.models.fitting.mocap.marker_ik import fill_gaps
from bodyfit.models.fitting.mocap.marker_sets import RAJAGOPAL_MARKERS, MarkerSetDef
from bodyfit.models.rotations import kabsch, zxy_angles
from bodyfit.models.skeleton.model import Skeleton, twin_name

MARKER_SIGMA = 0.01  # m: a marker residual of this size costs 1 (times its weight)
SCALE_SIGMA = 0.05  # prior on the per-segment log scale correction
SOFT_SIGMA = 0.15  # rad: prior on the soft (added spine / scapula) DOFs
RANGE_MARGIN = 0.02  # starting values are kept this fraction of the range inside the limits


@dataclass(frozen=True)
class VirtualMarkers:
    """Markers on the skeleton.

    Attributes:
        names: (M,); bodies: (M,) body names; local: (M, 3) body-frame points before scaling (m);
        anatomical: (M,) bool; weights: (M,) IK weights.
    """

    names: tuple[str, ...]
    bodies: tuple[str, ...]
    local: np.ndarray
    anatomical: np.ndarray
    weights: np.ndarray

    def subset(self, names: list[str]) -> VirtualMarkers:
        """The markers ``names`` in that order."""
        idx = [self.names.index(n) for n in names]
        return VirtualMarkers(
            tuple(names),
            tuple(self.bodies[i] for i in idx),
            self.local[idx],
            self.anatomical[idx],
            self.weights[idx],
        )

    def body_indices(self, skeleton: Skeleton) -> list[int]:
        return [skeleton.body_names.index(b) for b in self.bodies]


def virtual_markers(defn: MarkerSetDef, model: BodyModel) -> VirtualMarkers:
    """Default locations of a marker set's markers on our skeleton (see :mod:`.marker_sets`)."""
    skel = model.skeleton
    names = skel.body_names
    seg_of = skel.spec.body_segment_index
    zeros = np.zeros((1, skel.n_dof))
    unit = skel.forward(zeros).frames[0].double().numpy()  # unit scales: Rajagopal's own frames
    mean = model.forward(None, zeros, dtype=torch.float64)
    V = mean.vertices[0].numpy()
    F_mean, S_mean = mean.frames[0].numpy(), mean.scales[0].numpy()
    normals = vertex_normals(V, model.faces)
    lm_index = {n: int(i) for n, i in zip(model.landmark_names, model.data["landmarks"])}

    def to_local(frames: np.ndarray, body: int, world: np.ndarray) -> np.ndarray:
        return frames[body, :3, :3].T @ (world - frames[body, :3, 3])

    local = []
    for m in defn.markers:
        b = names.index(m.body)
        points = []
        for src in m.sources:
            kind, _, key = src.partition(":")
            if kind == "raj":
                raj_body, loc = RAJAGOPAL_MARKERS[key]
                F = unit[names.index(raj_body)]
                points.append(to_local(unit, b, F[:3, :3] @ np.asarray(loc) + F[:3, 3]))
            else:
                v = lm_index[key]
                if m.near is not None:
                    v = int(np.argmin(np.linalg.norm(V - (V[v] + np.asarray(m.near)), axis=1)))
                world = V[v] + m.offset * normals[v]
                points.append(to_local(F_mean, b, world) / S_mean[seg_of[b]])
        local.append(np.mean(points, axis=0))
    return VirtualMarkers(
        tuple(defn.names),
        tuple(m.body for m in defn.markers),
        np.asarray(local, np.float64),
        np.array([m.anatomical for m in defn.markers]),
        np.array([m.weight for m in defn.markers], np.float64),
    )


class ScaleModel:
    """``s = (s_mean + c P_b) * exp(r)`` with left/right tied corrections. Buffers only."""

    def __init__(self, model: BodyModel) -> None:
        self.mean = torch.as_tensor(np.asarray(model.data["scale_mean"], np.float64))  # (n_seg, 3)
        self.basis = torch.as_tensor(np.asarray(model.data["scale_basis"], np.float64))  # (K, n_seg, 3)
        segs = model.skeleton.segments
        firsts: list[str] = []
        for s in segs:
            key = min(s, twin_name(s))
            if key not in firsts:
                firsts.append(key)
        self.tie = torch.as_tensor([firsts.index(min(s, twin_name(s))) for s in segs])
        self.n_free = len(firsts)

    def centred(self, scales: np.ndarray) -> ScaleModel:
        """This model about a subject's ``scales`` (n_seg, 3) instead of the population mean, without the
        bone basis (one zero row): only the per-segment corrections move the scales."""
        out = copy.copy(self)
        out.mean = torch.as_tensor(np.asarray(scales, np.float64))
        out.basis = torch.zeros_like(self.basis[:1])
        return out

    def __call__(self, c: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
        """c: (K,), r: (n_free, 3) -> scales (n_seg, 3)."""
        return (self.mean + torch.einsum("k,ksc->sc", c, self.basis)) * torch.exp(r[self.tie])


@dataclass(frozen=True)
class DofPlan:
    """Which coordinates IK solves for. free: (F,) indices; locked: (n_dof,) values used for the others;
    soft: (n_dof,) prior weights (0 for none)."""

    free: np.ndarray
    locked: np.ndarray
    soft: np.ndarray

    @staticmethod
    def build(skel: Skeleton, defn: MarkerSetDef) -> DofPlan:
        locked = np.zeros(skel.n_dof)
        fixed = np.zeros(skel.n_dof, bool)
        for name, value in defn.locked:
            fixed[skel.dof_index(name)] = True
            locked[skel.dof_index(name)] = value
        soft = np.zeros(skel.n_dof)
        for name in defn.soft:
            soft[skel.dof_index(name)] = (MARKER_SIGMA / SOFT_SIGMA) ** 2
        return DofPlan(np.flatnonzero(~fixed), locked, soft)

    def holding(self, skel: Skeleton, values: Mapping[str, float]) -> DofPlan:
        """This plan with the coordinates ``values`` (name -> rad or m) locked at those values.

        Raises:
            KeyError: a name that is not one of ``skel``'s coordinates.
            ValueError: a value that is not finite or lies outside the coordinate's range.
        """
        locked = self.locked.copy()
        free = np.ones(skel.n_dof, bool)
        free[np.setdiff1d(np.arange(skel.n_dof), self.free)] = False
        for name, value in values.items():
            i = skel.dof_index(name)
            low, high = skel.ranges[i]
            if not (np.isfinite(value) and low <= value <= high):
                span = f"{value:.4g} is outside its range [{low:.4g}, {high:.4g}]"
                if skel.spec.coordinate(name).motion == "rotational":
                    low_deg, high_deg, value_deg = np.degrees([low, high, value])
                    span = (
                        f"{value:.4g} rad ({value_deg:.1f} degrees) is outside its range "
                        f"[{low:.4g}, {high:.4g}] rad ({low_deg:.1f} to {high_deg:.1f} degrees)"
                    )
                raise ValueError(f"{name} = {span}")
            locked[i], free[i] = float(value), False
        return DofPlan(np.flatnonzero(free), locked, self.soft)


def moved_bodies(skel: Skeleton, coordinates: Iterable[str]) -> np.ndarray:
    """(n_bodies,) bool: the bodies any of ``coordinates`` moves against its joint's parent (the joint's
    child and every body below it)."""
    spec = skel.spec
    parents = spec.body_parent_index
    out = np.zeros(len(parents), bool)
    for name in coordinates:
        out[spec.body_index(spec.joint(spec.coordinate(name).joint).child)] = True
    for b, p in enumerate(parents):  # a parent comes before its children
        out[b] |= p >= 0 and bool(out[p])
    return out


def pelvis_start(
    skel: Skeleton, markers: VirtualMarkers, scales: np.ndarray, observed: np.ndarray, times: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pelvis angles (tilt, list, rotation) and root per frame from the pelvis markers.

    The rigid alignment is :func:`~bodyfit.models.rotations.kabsch` (W. Kabsch, "A solution for the best
    rotation to relate two sets of vectors", Acta Crystallographica A 32(5), 1976).

    Args:
        scales: (n_seg, 3); observed: (T, M, 3); times: (T,).
    Returns:
        angles (T, 3) and root (T, 3); frames without 3 pelvis markers are interpolated.
    """
    on_pelvis = np.array([b == "pelvis" for b in markers.bodies])
    pelvis_seg = skel.spec.body_segment_index[skel.body_names.index("pelvis")]
    model_pts = markers.local[on_pelvis] * scales[pelvis_seg]
    R, t = kabsch(model_pts, observed[:, on_pelvis], markers.weights[on_pelvis])
    angles = zxy_angles(np.nan_to_num(R))
    angles[~np.isfinite(t).all(-1)] = np.nan
    if not np.isfinite(t).any():  # no frame shows 3 pelvis markers: start upright at the markers' centroid
        centre = np.nanmean(observed.reshape(-1, 3), axis=0)
        return np.zeros((len(times), 3)), np.tile(np.nan_to_num(centre), (len(times), 1))
    return fill_gaps(angles, times), fill_gaps(t, times)


def place_markers(
    skel: Skeleton,
    markers: VirtualMarkers,
    observed: np.ndarray,
    q: np.ndarray,
    root: np.ndarray,
    scales: np.ndarray,
    which: np.ndarray,
) -> VirtualMarkers:
    """Move markers ``which`` (M,) bool to where they were observed in a pose.

    Args:
        observed: (M, 3) (NaN: leave that marker where it is); q: (n_dof,); root: (3,); scales: (n_seg, 3).
    Returns:
        the markers with new body-frame locations (before scaling).
    """
    frames = skel.forward(q[None], root[None], scales[None]).frames[0].double().numpy()
    seg_of = skel.spec.body_segment_index
    local = markers.local.copy()
    for i, b in enumerate(markers.body_indices(skel)):
        if which[i] and np.isfinite(observed[i]).all():
            R, t = frames[b, :3, :3], frames[b, :3, 3]
            local[i] = R.T @ (observed[i] - t) / scales[seg_of[b]]
    return replace(markers, local=local)

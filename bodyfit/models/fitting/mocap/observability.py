"""Which coordinates a marker set can determine, and holding the others at a neutral prior.

A coordinate is observable when moving it moves the markers in a way no other coordinate can copy. Two
tests, on the calibrated subject in the poses of its calibration frames:

* no marker on the bodies the coordinate moves (its joint's child and everything below it): nothing can
  see it (a wrist without hand markers);
* its *distinct sensitivity* (:func:`distinct_sensitivity`), the displacement of the markers per radian
  that is left after the best compensation by every other free coordinate (paying its soft prior) and the
  root (the length of the Jacobian column orthogonal to the span of the others), is below
  :data:`MIN_SENSITIVITY` in most of those poses: the markers barely constrain it (a spine segment whose
  rotation the next one copies), so the solver would move it wherever noise and soft tissue push it,
  typically to a joint limit. Markers count with unit weight: the test is about geometry, not trust.

This is the local identifiability criterion of least-squares calibration (the diagonal of the inverse
Fisher information; e.g. J. Hollerbach, W. Khalil and M. Gautier, "Model Identification", in Springer
Handbook of Robotics, Springer, 2016, chapter 6).

Unobservable coordinates are reported with the reason and held by a soft prior at their neutral value (0,
the standing pose; every range holds it) instead of being solved into a limit.
"""

from __future__ import annotations

import numpy as np
import torch

from bodyfit.models.fitting.mocap.calibration import (
    MARKER_SIGMA,
    SOFT_SIGMA,
    DofPlan,
    VirtualMarkers,
    moved_bodies,
)
from bodyfit.models.fitting.mocap.marker_ik import MarkerChain, marker_jacobian
from bodyfit.models.skeleton.model import Skeleton

MIN_SENSITIVITY = 0.01  # m per rad: 10 degrees moving the markers by under 1.7 mm beyond what others explain
HOLD_WEIGHT = (MARKER_SIGMA / SOFT_SIGMA) ** 2  # the soft-DOF prior: 0.15 rad costs as much as 1 cm of marker


def distinct_sensitivity(
    skel: Skeleton,
    markers: VirtualMarkers,
    scales: np.ndarray,
    q: np.ndarray,
    root: np.ndarray,
    plan: DofPlan,
) -> np.ndarray:
    """(K, F) marker displacement per radian (or metre) of each free coordinate of ``plan`` that the other
    free coordinates and the root cannot reproduce, in each pose.

    The other coordinates' soft priors (``plan.soft``) make them pay for compensating, as in the IK; the
    coordinate's own prior is left out (it is not information from the markers): with ``H = J^T J +
    diag(soft)``, ``s_i^2 = 1 / (H^-1)_ii - soft_i``, the Schur complement of the others in ``J^T J``.

    Args:
        markers: the M markers (weight > 0 counts as 1); scales: (n_seg, 3); q: (K, n_dof); root: (K, 3).
    """
    fk = skel.kinematics(torch.float64)
    chain = MarkerChain.build(fk, markers.body_indices(skel))
    used = torch.as_tensor(markers.weights > 0, dtype=torch.float64)
    K, free = len(q), plan.free
    with torch.no_grad():
        _, jac, _ = marker_jacobian(
            fk, chain, torch.as_tensor(markers.local), torch.as_tensor(q), torch.as_tensor(root),
            torch.as_tensor(scales).expand(K, -1, -1),
        )  # fmt: skip
    cols = torch.cat([torch.as_tensor(free), torch.arange(skel.n_dof, skel.n_dof + 3)])
    J = (used[None, :, None, None] * jac[..., cols]).reshape(K, -1, len(cols))
    prior = torch.as_tensor(np.r_[plan.soft[free], np.zeros(3)])
    H = J.transpose(1, 2) @ J + torch.diag(prior + 1e-12)
    inv_diag = torch.diagonal(torch.linalg.inv(H), dim1=1, dim2=2)
    own = 1.0 / inv_diag.clamp_min(1e-30) - prior - 1e-12
    return torch.sqrt(own[:, : len(free)].clamp_min(0.0)).numpy()


def unobservable(
    skel: Skeleton,
    markers: VirtualMarkers,
    scales: np.ndarray,
    q: np.ndarray,
    root: np.ndarray,
    plan: DofPlan,
) -> dict[str, str]:
    """The free coordinates of ``plan`` that ``markers`` cannot determine, name -> reason (see the module
    docstring). q: (K, n_dof) and root: (K, 3) poses of the calibration frames; scales: (n_seg, 3)."""
    on_body = np.zeros(len(skel.body_names), int)
    for b, w in zip(markers.body_indices(skel), markers.weights):
        on_body[b] += w > 0
    out: dict[str, str] = {}
    sensitivity = np.median(distinct_sensitivity(skel, markers, scales, q, root, plan), axis=0)
    for k, i in enumerate(plan.free):
        name = skel.dof_names[i]
        moved = moved_bodies(skel, [name])
        if on_body[moved].sum() == 0:
            child = skel.spec.joint(skel.spec.coordinate(name).joint).child
            out[name] = f"no marker on {child} or the bodies it carries"
        elif sensitivity[k] < MIN_SENSITIVITY:
            unit = "mm per degree" if skel.spec.coordinate(name).motion == "rotational" else "mm per mm"
            scale = np.radians(1.0) * 1000 if unit == "mm per degree" else 1.0
            out[name] = (
                f"its markers move {sensitivity[k] * scale:.2f} {unit} beyond what the other coordinates "
                f"explain (at least {MIN_SENSITIVITY * scale:.2f} needed)"
            )
    return out


def holding_neutral(skel: Skeleton, plan: DofPlan, names: list[str]) -> DofPlan:
    """``plan`` with a soft prior of weight :data:`HOLD_WEIGHT` pulling the coordinates ``names`` towards 0
    (their neutral value), added to any prior they already have."""
    soft = plan.soft.copy()
    for name in names:
        i = skel.dof_index(name)
        soft[i] = max(soft[i], HOLD_WEIGHT)
    return DofPlan(plan.free, plan.locked, soft)


AT_LIMIT = np.radians(0.5)  # a coordinate this close to a limit counts as at it
AT_LIMIT_SHARE = 0.5  # ... reported when it is so in more than this share of the frames


def at_limits(skel: Skeleton, q: np.ndarray, plan: DofPlan, held: dict[str, str]) -> dict[str, float]:
    """Free coordinates of ``plan`` (not ``held``) within :data:`AT_LIMIT` of a joint limit in more than
    :data:`AT_LIMIT_SHARE` of the frames of ``q`` (T, n_dof): name -> that share of frames. A coordinate
    the markers observe yet keep at a limit is pulled beyond it: a marker named or placed otherwise than
    the set defines it, or a coordinate whose zero differs from the lab's model."""
    out: dict[str, float] = {}
    for i in plan.free:
        name = skel.dof_names[i]
        if name in held or skel.spec.coordinate(name).motion != "rotational":
            continue
        share = float((np.abs(q[:, i, None] - skel.ranges[i][None]).min(axis=1) < AT_LIMIT).mean())
        if share > AT_LIMIT_SHARE:
            out[name] = share
    return out

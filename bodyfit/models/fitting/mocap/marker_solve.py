"""Inverse kinematics of every frame at once: weighted marker least squares in the bounded coordinates.

Unknowns per frame: the free coordinates, kept inside their joint limits by a box-constrained solver (the
limits are never violated; see :func:`~.marker_ik.levenberg_marquardt` for why not a tanh mapping here),
and the root translation. Residuals: ``sqrt(w_m) (x_m - y_m)`` for every visible marker (missing
ones are masked to zero) and ``sqrt(lambda_i) q_i`` for the soft DOFs. Frames are independent problems
solved together by :func:`~.marker_ik.levenberg_marquardt` (one batched Jacobian per iteration). Warm
start, the batched form of OpenSim's frame-to-frame warm start: the pelvis of every frame from its markers
(Kabsch; :func:`~.calibration.pelvis_start`), the other DOFs neutral (or ``start``); a staged first pass on
every ``stride``-th frame, then every frame starts from the solution interpolated between its neighbours in
that pass. The objective is that of OpenSim's inverse kinematics (A. Seth et al., "OpenSim: Simulating
musculoskeletal dynamics and neuromuscular control to study human and animal movement", PLoS Computational
Biology 14(7), 2018), with the joint limits as hard bounds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bodyfit.models.fitting.mocap.calibration import RANGE_MARGIN, DofPlan, VirtualMarkers, pelvis_start
from bodyfit.models.fitting.mocap.marker_ik import (
    MarkerChain,
    levenberg_marquardt,
    marker_jacobian,
    marker_positions,
)
from bodyfit.models.skeleton.model import Skeleton

COARSE_STRIDE = 6
DISTAL_ROOTS = ("scapulothoracic_link_r", "scapulothoracic_link_l", "cervical_link")  # arms, head


@dataclass(frozen=True)
class IKSolution:
    """q: (T, n_dof); root: (T, 3); errors: (T, M) marker distances (m, NaN where missing);
    iterations: LM iterations of the longest frame over both passes; evaluations: Jacobian evaluations
    per frame (mean)."""

    q: np.ndarray
    root: np.ndarray
    errors: np.ndarray
    iterations: int
    evaluations: float


class MarkerProblem:
    """Residuals and Jacobians of the marker IK for a subset of frames (holds tensors, no state).

    ``free`` (F,) are the DOFs solved for; every other DOF keeps its value in ``base`` (T, n_dof).
    """

    def __init__(
        self,
        skel: Skeleton,
        markers: VirtualMarkers,
        scales: np.ndarray,
        observed: np.ndarray,
        free: np.ndarray,
        soft: np.ndarray,
        base: np.ndarray,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        self.skel = skel
        self.fk = skel.kinematics(dtype)
        self.chain = MarkerChain.build(self.fk, markers.body_indices(skel))
        self.local = torch.as_tensor(markers.local, dtype=dtype)
        self.scales = torch.as_tensor(scales, dtype=dtype)
        seen = np.isfinite(observed).all(-1)  # (T, M)
        self.target = torch.as_tensor(np.where(seen[..., None], observed, 0.0), dtype=dtype)
        self.sqrt_w = torch.as_tensor(np.sqrt(markers.weights)[None] * seen, dtype=dtype)  # (T, M)
        self.free = torch.as_tensor(free)
        self.base = torch.as_tensor(base, dtype=dtype)
        soft_cols = np.flatnonzero(soft[free] > 0)
        self.soft_cols = torch.as_tensor(soft_cols)
        self.sqrt_soft = torch.as_tensor(np.sqrt(soft[free][soft_cols]), dtype=dtype)
        inf = torch.full((3,), torch.inf, dtype=dtype)
        self.lower = torch.cat([torch.as_tensor(skel.ranges[free, 0], dtype=dtype), -inf])
        self.upper = torch.cat([torch.as_tensor(skel.ranges[free, 1], dtype=dtype), inf])
        self.n_free = len(free)
        self.cols = torch.cat([self.free, torch.arange(skel.n_dof, skel.n_dof + 3)])

    def coordinates(self, x: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x (b, F + 3) of frames ``rows`` -> q (b, n_dof), root (b, 3)."""
        q = self.base[rows].clone()
        q[:, self.free] = x[:, : self.n_free]
        return q, x[:, self.n_free :]

    def __call__(self, x: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Residuals (b, 3M + n_soft) and Jacobian (b, 3M + n_soft, F + 3) of frames ``rows``."""
        b = x.shape[0]
        q, root = self.coordinates(x, rows)
        scales = self.scales.expand(b, -1, -1)
        pos, jac, _ = marker_jacobian(self.fk, self.chain, self.local, q, root, scales)
        w = self.sqrt_w[rows].unsqueeze(-1)  # (b, M, 1)
        r_m = (w * (pos - self.target[rows])).reshape(b, -1)
        J = (w.unsqueeze(-1) * jac[..., self.cols]).reshape(b, r_m.shape[1], -1)
        r_s = self.sqrt_soft * x[:, self.soft_cols]
        J_s = x.new_zeros(b, len(self.soft_cols), J.shape[-1])
        J_s[:, torch.arange(len(self.soft_cols)), self.soft_cols] = self.sqrt_soft
        return torch.cat([r_m, r_s], dim=1), torch.cat([J, J_s], dim=1)


def marker_errors(
    skel: Skeleton, markers: VirtualMarkers, scales: np.ndarray, q: np.ndarray, root: np.ndarray,
    observed: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """(T, M) distances of the model markers to the observed ones (m; NaN where missing).

    Args:
        scales: (n_seg, 3); q: (T, n_dof); root: (T, 3); observed: (T, M, 3).
    """
    fk = skel.kinematics(torch.float64)
    chain = MarkerChain.build(fk, markers.body_indices(skel))
    with torch.no_grad():
        pos = marker_positions(
            fk, chain, torch.as_tensor(markers.local), torch.as_tensor(q), torch.as_tensor(root),
            torch.as_tensor(scales).expand(len(q), -1, -1),
        ).numpy()  # fmt: skip
    return np.linalg.norm(pos - observed, axis=-1)


def distal_dofs(skel: Skeleton) -> np.ndarray:
    """(n_dof,) bool: DOFs that move only the head or an arm (their joints lie below
    :data:`DISTAL_ROOTS`)."""
    distal = distal_bodies(skel)
    return np.array(
        [skel.body_names.index(skel.spec.joint(c.joint).child) in distal for c in skel.spec.coordinates]
    )


def distal_bodies(skel: Skeleton) -> set[int]:
    """Indices of the bodies at or below :data:`DISTAL_ROOTS` (arms and head)."""
    parents = skel.spec.body_parent_index
    roots = {skel.body_names.index(n) for n in DISTAL_ROOTS if n in skel.body_names}
    out = set()
    for b in range(len(parents)):
        j = b
        while j >= 0 and j not in roots:
            j = parents[j]
        if j >= 0:
            out.add(b)
    return out


def _solve(
    skel: Skeleton,
    markers: VirtualMarkers,
    scales: np.ndarray,
    observed: np.ndarray,
    free: np.ndarray,
    soft: np.ndarray,
    q: np.ndarray,
    root: np.ndarray,
    max_iterations: int,
) -> tuple[np.ndarray, np.ndarray, int, float]:
    """One LM pass over all frames of ``observed`` (T, M, 3) from q (T, n_dof), root (T, 3)."""
    problem = MarkerProblem(skel, markers, scales, observed, free, soft, q)
    x = torch.cat([torch.as_tensor(q[:, free]), torch.as_tensor(root)], dim=1)
    res = levenberg_marquardt(problem, x, problem.lower, problem.upper, max_iterations)
    with torch.no_grad():
        qt, rt = problem.coordinates(res.x, torch.arange(len(q)))
    return qt.numpy().copy(), rt.numpy().copy(), res.iterations, res.evaluations


def solve_ik(
    skel: Skeleton,
    markers: VirtualMarkers,
    scales: np.ndarray,
    observed: np.ndarray,
    times: np.ndarray,
    plan: DofPlan,
    start: np.ndarray | None = None,
    max_iterations: int = 50,
    stride: int = COARSE_STRIDE,
) -> IKSolution:
    """Coordinates of every frame.

    Staged on the first pass (every ``stride``-th frame): pelvis, legs and trunk from their markers; then
    arms and head with the rest held; then everything. All frames then start from the interpolated
    first-pass solution for one last pass (the torso / limbs / all staging of Wang et al., "BLSM: A
    Bone-Level Skinned Model of the Human Mesh", ECCV 2020, batched over frames).

    Args:
        markers: the M markers of ``observed``; scales: (n_seg, 3); observed: (T, M, 3) (NaN: missing);
        times: (T,); plan: free / locked / soft DOFs; start: (n_dof,) starting pose or None (neutral);
        stride: frames of the first pass (1: every frame).
    Returns:
        :class:`IKSolution`.
    """
    T = observed.shape[0]
    angles, root0 = pelvis_start(skel, markers, scales, observed, times)
    q0 = np.tile(plan.locked if start is None else start, (T, 1))
    q0[:, :3] = angles
    q0 = skel.inside(q0, RANGE_MARGIN)
    coarse = np.unique(np.r_[np.arange(0, T, max(stride, 1)), T - 1])
    distal_b = distal_bodies(skel)
    is_distal = np.array([b in distal_b for b in markers.body_indices(skel)])
    core = markers.subset([n for n, d in zip(markers.names, is_distal) if not d])
    distal_free = np.intersect1d(plan.free, np.flatnonzero(distal_dofs(skel)))
    q, root = q0[coarse], root0[coarse]
    obs = observed[coarse]
    iterations, evaluations = 0, 0.0
    stages = [(core, obs[:, ~is_distal], plan.free)] if is_distal.any() else []
    if is_distal.any() and len(distal_free):
        stages.append((markers, obs, distal_free))
    stages.append((markers, obs, plan.free))
    for stage_markers, stage_obs, free in stages:
        q, root, it, ev = _solve(
            skel, stage_markers, scales, stage_obs, free, plan.soft, q, root, max_iterations
        )
        iterations, evaluations = iterations + it, evaluations + ev * len(coarse) / T
    if len(coarse) < T:
        xc = np.concatenate([q, root], axis=1)
        x = np.stack([np.interp(times, times[coarse], xc[:, k]) for k in range(xc.shape[1])], -1)
        q, root, it, ev = _solve(
            skel, markers, scales, observed, plan.free, plan.soft, x[:, : skel.n_dof], x[:, skel.n_dof :],
            max_iterations,
        )  # fmt: skip
        iterations, evaluations = iterations + it, evaluations + ev
    errors = marker_errors(skel, markers, scales, q, root, observed)
    return IKSolution(q, root, errors, iterations, evaluations)

"""Inverse kinematics of every frame at once: weighted marker least squares in the bounded coordinates.

Unknowns per frame: the free coordinates, kept inside their joint limits by a box-constrained solver (the
limits are never violated; see :func:`~.marker_ik.levenberg_marquardt` for why not a tanh mapping here),
and the root translation. Residuals: ``sqrt(w_m) (x_m - y_m)`` for every visible marker (missing
ones are masked to zero) and ``sqrt(lambda_i) q_i`` for the soft DOFs. Frames are independent problems
solved together by :func:`~.marker_ik.levenberg_marquardt` (one batched Jacobian per iteration). Warm
start: the pelvis of every frame from its markers (Kabsch), the other DOFs from the static pose; a first
pass on every ``stride``-th frame, then all frames start from the interpolated solution.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bodyfit.models.fitting.calibration import DofPlan, VirtualMarkers, inside, pelvis_start
from bodyfit.models.fitting.marker_ik import MarkerChain, levenberg_marquardt, marker_jacobian
from bodyfit.models.skeleton.model import Skeleton

COARSE_STRIDE = 6


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
    """Residuals and Jacobians of the marker IK for a subset of frames (holds tensors, no state)."""

    def __init__(
        self,
        skel: Skeleton,
        markers: VirtualMarkers,
        scales: np.ndarray,
        observed: np.ndarray,
        plan: DofPlan,
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
        self.free = torch.as_tensor(plan.free)
        self.locked = torch.as_tensor(plan.locked, dtype=dtype)
        soft = np.flatnonzero(plan.soft[plan.free] > 0)
        self.soft_cols = torch.as_tensor(soft)
        self.sqrt_soft = torch.as_tensor(np.sqrt(plan.soft[plan.free][soft]), dtype=dtype)
        inf = torch.full((3,), torch.inf, dtype=dtype)
        self.lower = torch.cat([torch.as_tensor(skel.ranges[:, 0], dtype=dtype)[self.free], -inf])
        self.upper = torch.cat([torch.as_tensor(skel.ranges[:, 1], dtype=dtype)[self.free], inf])
        self.n_free = len(plan.free)

    def coordinates(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x (b, F + 3) -> q (b, n_dof), root (b, 3)."""
        q = self.locked.expand(x.shape[0], -1).clone()
        q[:, self.free] = x[:, : self.n_free]
        return q, x[:, self.n_free :]

    def __call__(self, x: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Residuals (b, 3M + n_soft) and Jacobian (b, 3M + n_soft, F + 3) of frames ``rows``."""
        b = x.shape[0]
        q, root = self.coordinates(x)
        scales = self.scales.expand(b, -1, -1)
        pos, jac, _ = marker_jacobian(self.fk, self.chain, self.local, q, root, scales)
        w = self.sqrt_w[rows].unsqueeze(-1)  # (b, M, 1)
        r_m = (w * (pos - self.target[rows])).reshape(b, -1)
        cols = torch.cat([self.free, torch.arange(self.skel.n_dof, self.skel.n_dof + 3)])
        J = (w.unsqueeze(-1) * jac[..., cols]).reshape(b, r_m.shape[1], -1)
        r_s = self.sqrt_soft * x[:, self.soft_cols]
        J_s = x.new_zeros(b, len(self.soft_cols), J.shape[-1])
        J_s[:, torch.arange(len(self.soft_cols)), self.soft_cols] = self.sqrt_soft
        return torch.cat([r_m, r_s], dim=1), torch.cat([J, J_s], dim=1)

    def errors(self, q: np.ndarray, root: np.ndarray, observed: np.ndarray) -> np.ndarray:
        """(T, M) distances of the model markers to the observed ones (NaN where missing)."""
        from bodyfit.models.fitting.marker_ik import marker_positions

        with torch.no_grad():
            dt = self.local.dtype
            T = q.shape[0]
            pos = marker_positions(
                self.fk, self.chain, self.local, torch.as_tensor(q, dtype=dt),
                torch.as_tensor(root, dtype=dt), self.scales.expand(T, -1, -1),
            ).numpy()  # fmt: skip
        return np.linalg.norm(pos - observed, axis=-1)


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

    Args:
        markers: the M markers of ``observed``; scales: (n_seg, 3); observed: (T, M, 3) (NaN: missing);
        times: (T,); plan: free / locked / soft DOFs; start: (n_dof,) starting pose (the static pose) or
        None (neutral); stride: frames of the first pass (1: a single pass).
    Returns:
        :class:`IKSolution`.
    """
    T = observed.shape[0]
    problem = MarkerProblem(skel, markers, scales, observed, plan)
    angles, root0 = pelvis_start(skel, markers, scales, observed, times)
    q0 = np.tile(plan.locked if start is None else start, (T, 1))
    q0[:, :3] = angles
    q0 = inside(skel, q0)
    x = torch.cat([torch.as_tensor(q0[:, plan.free]), torch.as_tensor(root0)], dim=1)
    iterations, evaluations = 0, 0.0
    if stride > 1 and 2 * stride < T:
        coarse = np.unique(np.r_[np.arange(0, T, stride), T - 1])
        rows = torch.as_tensor(coarse)

        def sub(xs: torch.Tensor, r: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            return problem(xs, rows[r])

        first = levenberg_marquardt(sub, x[rows], problem.lower, problem.upper, max_iterations)
        iterations += first.iterations
        evaluations += first.evaluations * len(coarse) / T
        xc = first.x.numpy()
        x = torch.as_tensor(
            np.stack([np.interp(times, times[coarse], xc[:, k]) for k in range(xc.shape[1])], -1)
        )
    final = levenberg_marquardt(problem, x, problem.lower, problem.upper, max_iterations)
    with torch.no_grad():
        q, root = problem.coordinates(final.x)
    qn, rn = q.numpy().copy(), root.numpy().copy()
    return IKSolution(
        qn,
        rn,
        problem.errors(qn, rn, observed),
        iterations + final.iterations,
        evaluations + final.evaluations,
    )

"""Subject calibration: segment scales, marker locations and the poses of a few frames, fitted together.

Unknowns: the pose of each of K frames (free coordinates, box-bounded by the joint limits, and root), and
the shared subject parameters ``z = [c, r, l]``: bone coefficients ``c`` and per-segment log corrections
``r`` of the scales (:class:`~.calibration.ScaleModel`), and the body-frame locations ``l`` of the
markers being placed. Residuals (metres): ``sqrt(w_m) (x_m - y_m)`` per visible marker and frame; priors
``sigma_m c``, ``sigma_m r / SCALE_SIGMA``, ``sigma_m (l - l_0) / PLACE_SIGMA`` and the soft DOFs.

The normal equations have the bundle-adjustment structure (one small pose block per frame, a shared
block; B. Triggs, P. F. McLauchlan, R. I. Hartley and A. W. Fitzgibbon, "Bundle Adjustment - A Modern
Synthesis", Vision Algorithms: Theory and Practice, LNCS 1883, Springer, 2000), so each Levenberg-Marquardt
step (:mod:`.marker_ik`) eliminates the poses with a batched Schur complement. All Jacobians are analytic
(:func:`~.marker_ik.marker_jacobian`, positions are linear in the scales).

* From a static trial (the ScaleTool + MarkerPlacer of S. L. Delp et al., "OpenSim: Open-Source Software to
  Create and Analyze Dynamic Simulations of Movement", IEEE Transactions on Biomedical Engineering 54(11),
  2007): K = 1 (the mean of the static frames), the anatomical markers at their default locations fix
  scales and standing pose; afterwards every marker seen is placed where it was observed.
* Without a static trial: K frames spread over the motion, all markers used, the technical markers'
  locations estimated with the rest (functional calibration: thigh and shank clusters must move rigidly
  about hip, knee and ankle), anatomical markers kept at their defaults.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from bodyfit.models.fitting.mocap.calibration import (
    MARKER_SIGMA,
    RANGE_MARGIN,
    SCALE_SIGMA,
    DofPlan,
    ScaleModel,
    VirtualMarkers,
    pelvis_start,
)
from bodyfit.models.fitting.mocap.marker_ik import MarkerChain, marker_jacobian, marker_positions
from bodyfit.models.skeleton.model import Skeleton

PLACE_SIGMA = 0.03  # m: prior on how far a technical marker sits from its default location


@dataclass(frozen=True)
class Calibration:
    """scales: (n_seg, 3); markers: the calibrated markers; q: (K, n_dof) and root: (K, 3) poses of the
    calibration frames; errors: (K, M) marker distances (m, NaN where missing); iterations: LM steps."""

    scales: np.ndarray
    markers: VirtualMarkers
    q: np.ndarray
    root: np.ndarray
    errors: np.ndarray
    iterations: int


class _Problem:
    """Residuals and Jacobians of the calibration (tensors only; the solver keeps the state)."""

    def __init__(
        self,
        skel: Skeleton,
        scale_model: ScaleModel,
        markers: VirtualMarkers,
        observed: np.ndarray,
        plan: DofPlan,
        place: np.ndarray,
        scale_sigma: float | np.ndarray = SCALE_SIGMA,
    ) -> None:
        dt = torch.float64
        self.skel, self.sm, self.plan = skel, scale_model, plan
        self.fk = skel.kinematics(dt)
        self.chain = MarkerChain.build(self.fk, markers.body_indices(skel))
        seen = np.isfinite(observed).all(-1)
        self.target = torch.as_tensor(np.where(seen[..., None], observed, 0.0))
        self.sqrt_w = torch.as_tensor(np.sqrt(markers.weights)[None] * seen)
        self.free = torch.as_tensor(plan.free)
        self.locked = torch.as_tensor(plan.locked)
        self.soft = torch.as_tensor(np.sqrt(plan.soft[plan.free]))
        self.l0 = torch.as_tensor(markers.local)
        self.place = torch.as_tensor(np.flatnonzero(place))
        self.n_b, self.n_r, self.n_l = (
            scale_model.basis.shape[0],
            scale_model.n_free * 3,
            3 * int(place.sum()),
        )
        self.n_z = self.n_b + self.n_r + self.n_l
        sigma = np.broadcast_to(np.asarray(scale_sigma, np.float64), (scale_model.n_free, 3))
        self.scale_prior = torch.as_tensor(MARKER_SIGMA / sigma.reshape(-1))
        inf = torch.full((3,), torch.inf, dtype=dt)
        self.lower = torch.cat([torch.as_tensor(skel.ranges[plan.free, 0]), -inf])
        self.upper = torch.cat([torch.as_tensor(skel.ranges[plan.free, 1]), inf])
        self.F = len(plan.free)

    def unpack(self, x: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """x (K, F + 3), z (n_z,) -> q (K, n_dof), root (K, 3), c, r (n_free, 3), local (M, 3)."""
        q = self.locked.expand(x.shape[0], -1).clone()
        q[:, self.free] = x[:, : self.F]
        c = z[: self.n_b]
        r = z[self.n_b : self.n_b + self.n_r].reshape(-1, 3)
        local = self.l0.clone()
        local[self.place] = z[self.n_b + self.n_r :].reshape(-1, 3)
        return q, x[:, self.F :], c, r, local

    def __call__(
        self, x: torch.Tensor, z: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Frame residuals (K, R), pose Jacobian (K, R, F + 3), shared Jacobian (K, R, n_z), prior
        residuals (n_z,) and their (diagonal) Jacobian (n_z,)."""
        K = x.shape[0]
        q, root, c, r, local = self.unpack(x, z)
        s = self.sm(c, r)
        pos, jq, js = marker_jacobian(self.fk, self.chain, local, q, root, s.expand(K, -1, -1), True)
        assert js is not None
        w = self.sqrt_w.unsqueeze(-1)
        res = (w * (pos - self.target)).reshape(K, -1)
        cols = torch.cat([self.free, torch.arange(self.skel.n_dof, self.skel.n_dof + 3)])
        Jp = (w.unsqueeze(-1) * jq[..., cols]).reshape(K, res.shape[1], -1)
        # Shared: scales through c and r, then the placed markers' locations.
        e = torch.exp(r[self.sm.tie])  # (n_seg, 3)
        jc = torch.einsum("kmxsa,bsa->kmxb", js, self.sm.basis * e)
        jr_full = js * s  # (K, M, 3, n_seg, 3): d/d r of the segment's own factor
        jr = jr_full.new_zeros(*jr_full.shape[:3], self.sm.n_free, 3).index_add_(3, self.sm.tie, jr_full)
        frames_R = self.fk(q, root, s.expand(K, -1, -1)).frames[:, self.chain.body[self.place], :3, :3]
        seg = self.chain.segment[self.place]
        jl = pos.new_zeros(K, pos.shape[1], 3, len(self.place), 3)
        jl[:, self.place, :, torch.arange(len(self.place)), :] = (
            frames_R.transpose(0, 1) * s[seg][:, None, None, :]
        )
        Jz = torch.cat([jc, jr.flatten(3), jl.flatten(3)], dim=-1)
        Jz = (w.unsqueeze(-1) * Jz).reshape(K, res.shape[1], -1)
        # Soft DOFs ride along with the frames; priors on z are diagonal.
        soft = self.soft * x[:, : self.F]
        Js = torch.zeros(K, self.F, Jp.shape[-1], dtype=x.dtype)
        Js[:, torch.arange(self.F), torch.arange(self.F)] = self.soft
        res = torch.cat([res, soft], dim=1)
        Jp = torch.cat([Jp, Js], dim=1)
        Jz = torch.cat([Jz, Jz.new_zeros(K, self.F, self.n_z)], dim=1)
        dz = torch.cat(
            [
                torch.full((self.n_b,), MARKER_SIGMA, dtype=z.dtype),
                self.scale_prior.to(z.dtype),
                torch.full((self.n_l,), MARKER_SIGMA / PLACE_SIGMA, dtype=z.dtype),
            ]
        )
        z0 = torch.cat([torch.zeros(self.n_b + self.n_r, dtype=z.dtype), self.l0[self.place].flatten()])
        return res, Jp, Jz, dz * (z - z0), dz


def _schur_lm(
    problem: _Problem, x: torch.Tensor, z: torch.Tensor, max_iterations: int, rtol: float = 1e-9
) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Levenberg-Marquardt on (x, z) with the poses eliminated by a Schur complement. Returns x, z, steps.

    K. Levenberg, "A method for the solution of certain non-linear problems in least squares", Quarterly of
    Applied Mathematics 2(2), 1944; D. W. Marquardt, "An algorithm for least-squares estimation of nonlinear
    parameters", Journal of the Society for Industrial and Applied Mathematics 11(2), 1963; the elimination as
    in bundle adjustment (Triggs et al., see the module docstring).
    """

    def evaluate(xv: torch.Tensor, zv: torch.Tensor) -> tuple[torch.Tensor, ...]:
        res, Jp, Jz, rz, dz = problem(xv, zv)
        return res, Jp, Jz, rz, dz, 0.5 * ((res * res).sum() + (rz * rz).sum())

    state = evaluate(x, z)
    lam, steps = 1e-3, 0
    lo, hi = problem.lower, problem.upper
    for _ in range(max_iterations):
        res, Jp, Jz, rz, dz, cost = state
        steps += 1
        Hpp = Jp.transpose(1, 2) @ Jp
        Hpz = Jp.transpose(1, 2) @ Jz
        Hzz = torch.einsum("kri,krj->ij", Jz, Jz) + torch.diag(dz * dz)
        gp = (Jp.transpose(1, 2) @ res.unsqueeze(-1)).squeeze(-1)
        gz = torch.einsum("kri,kr->i", Jz, res) + dz * rz
        held = ((x <= lo) & (gp > 0)) | ((x >= hi) & (gp < 0))
        keep = (~held).to(x.dtype)
        Hpp = Hpp * keep.unsqueeze(1) * keep.unsqueeze(2) + torch.diag_embed(1.0 - keep)
        Hpz, gp = Hpz * keep.unsqueeze(-1), gp * keep
        Hpp = Hpp + lam * torch.diag_embed(torch.diagonal(Hpp, dim1=1, dim2=2) + 1e-12)
        Hzz = Hzz + lam * torch.diag(torch.diagonal(Hzz) + 1e-12)
        Ap = torch.linalg.solve(Hpp, torch.cat([Hpz, gp.unsqueeze(-1)], dim=-1))  # (K, P, n_z + 1)
        S = Hzz - torch.einsum("kpi,kpj->ij", Hpz, Ap[..., :-1])
        rhs = -gz + torch.einsum("kpi,kp->i", Hpz, Ap[..., -1])
        step_z = torch.linalg.solve(S, rhs)
        step_x = -(Ap[..., -1] + Ap[..., :-1] @ step_z)
        x_new = torch.maximum(torch.minimum(x + step_x, hi), lo)
        z_new = z + step_z
        new = evaluate(x_new, z_new)
        if bool(torch.isfinite(new[-1])) and new[-1] <= cost:
            gain = float(cost - new[-1])
            x, z, state, lam = x_new, z_new, new, max(lam / 3, 1e-9)
            if gain <= rtol * float(cost):
                break
        else:
            lam *= 4
            if lam > 1e9:
                break
    return x, z, steps


def calibrate(
    skel: Skeleton,
    scale_model: ScaleModel,
    markers: VirtualMarkers,
    observed: np.ndarray,
    times: np.ndarray,
    plan: DofPlan,
    place: np.ndarray,
    start: np.ndarray | None = None,
    max_iterations: int = 60,
    scale_sigma: float | np.ndarray = SCALE_SIGMA,
) -> Calibration:
    """Fit scales, the locations of markers ``place`` and the poses of K frames.

    Args:
        markers: M markers (their weights are the fit weights; weight 0 leaves a marker out);
        observed: (K, M, 3) positions (NaN: missing); times: (K,); plan: free / locked / soft DOFs;
        place: (M,) bool, markers whose locations are estimated; start: (K, n_dof) starting poses or
            None (pelvis from its markers, the rest neutral); scale_sigma: prior on the per-segment log
            scale corrections (about ``scale_model``'s mean): one value, or (n_free, 3) per tied segment.
    Returns:
        :class:`Calibration` (markers with their estimated locations).
    """
    problem = _Problem(skel, scale_model, markers, observed, plan, place, scale_sigma)
    mean = scale_model.mean.numpy()
    angles, root0 = pelvis_start(skel, markers, mean, observed, times)
    q0 = np.tile(plan.locked, (len(times), 1)) if start is None else start.copy()
    if start is None:
        q0[:, :3] = angles
    q0 = skel.inside(q0, RANGE_MARGIN)
    x = torch.cat([torch.as_tensor(q0[:, plan.free]), torch.as_tensor(root0)], dim=1)
    z = torch.cat(
        [torch.zeros(problem.n_b + problem.n_r, dtype=torch.float64), problem.l0[problem.place].flatten()]
    )
    x, z, steps = _schur_lm(problem, x, z, max_iterations)
    with torch.no_grad():
        q, root, c, r, local = problem.unpack(x, z)
        s = scale_model(c, r)
        pos = marker_positions(problem.fk, problem.chain, local, q, root, s.expand(len(q), -1, -1))
    errors = np.linalg.norm(pos.numpy() - observed, axis=-1)
    errors[:, markers.weights <= 0] = np.nan
    return Calibration(
        s.numpy(), replace(markers, local=local.numpy()), q.numpy(), root.numpy(), errors, steps
    )

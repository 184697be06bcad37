"""Marker kinematics and a batched Levenberg-Marquardt solver (pure functions, torch).

Levenberg-Marquardt: K. Levenberg, "A method for the solution of certain non-linear problems in least
squares", Quarterly of Applied Mathematics 2(2), 1944; D. W. Marquardt, "An algorithm for least-squares
estimation of nonlinear parameters", Journal of the Society for Industrial and Applied Mathematics 11(2),
1963.

Marker positions are body-fixed points: ``x_m = R_b (l_m * s_seg(b)) + t_b`` with ``l_m`` the point in
body ``b``'s frame before segment scaling. Their Jacobian with respect to every coordinate is analytic:
a joint's rotation axis ``k`` (world direction ``w_k``, about the origin ``o_M`` of the joint's moving
frame) moves a downstream point by ``f'_k(q) w_k x (x - o_M)``; a translation axis by ``f'_k(q) b_k``.
``f'`` (the derivative of each transform axis' function) comes from one forward-mode pass through the
compiled function table. One Jacobian costs about two forward kinematics, so Gauss-Newton steps on all
frames at once are cheap; frames are independent, so each has its own damping and stops on its own.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from bodyfit.models.body.model import body_points
from bodyfit.models.rotations import axis_angle_matrix
from bodyfit.models.skeleton.kinematics import SkeletonKinematics

ARC_SMALL = 1e-3  # below this |x| the arc basis uses its Taylor series (as functions.arc_basis)


@dataclass(frozen=True)
class MarkerChain:
    """Which transform axes move which marker (precomputed once per marker set).

    Attributes:
        body, segment: (M,) body and scale-segment index of each marker.
        pair_marker, pair_joint, pair_slot, pair_column: (P,) one entry per (marker, ancestor joint axis):
            the marker, the joint, the axis slot (0-2 rotations, 3-5 translations) and the column of
            ``[q, root]`` that drives it.
        n_columns: n_dof + 3.
        anc_marker, anc_joint: (A,) every (marker, ancestor joint) pair, for the scale Jacobian.
    """

    body: torch.Tensor
    segment: torch.Tensor
    pair_marker: torch.Tensor
    pair_joint: torch.Tensor
    pair_slot: torch.Tensor
    pair_column: torch.Tensor
    n_columns: int
    anc_marker: torch.Tensor
    anc_joint: torch.Tensor

    @staticmethod
    def build(fk: SkeletonKinematics, bodies: list[int]) -> MarkerChain:
        """Chains of the markers on ``bodies`` (body indices) through ``fk``'s tree."""
        spec = fk.spec
        parents = spec.body_parent_index
        seg_of = spec.body_segment_index
        cols = fk.cols.reshape(len(spec.joints), 6).tolist()
        zero_col = fk.n_dof + 3
        pm, pj, ps, pc, am, aj = [], [], [], [], [], []
        for m, b in enumerate(bodies):
            j = b
            while j >= 0:  # joint j moves body j
                am.append(m)
                aj.append(j)
                for slot in range(6):
                    if cols[j][slot] != zero_col:
                        pm.append(m)
                        pj.append(j)
                        ps.append(slot)
                        pc.append(cols[j][slot])
                j = parents[j]

        def t(v: list[int]) -> torch.Tensor:
            return torch.as_tensor(v, dtype=torch.long)

        segs = [seg_of[b] for b in bodies]
        return MarkerChain(t(bodies), t(segs), t(pm), t(pj), t(ps), t(pc), fk.n_dof + 3, t(am), t(aj))


def marker_positions(
    fk: SkeletonKinematics,
    chain: MarkerChain,
    local: torch.Tensor,
    q: torch.Tensor,
    root: torch.Tensor,
    scales: torch.Tensor,
) -> torch.Tensor:
    """World marker positions.

    Args:
        local: (M, 3) or (B, M, 3) points in their body frames before scaling; q: (B, n_dof);
            root: (B, 3); scales: (B, n_seg, 3).
    Returns:
        (B, M, 3).
    """
    return body_points(fk(q, root, scales).frames, scales, chain.body, chain.segment, local)


def table_with_slope(x: torch.Tensor, fk: SkeletonKinematics) -> tuple[torch.Tensor, torch.Tensor]:
    """Every transform-axis function of ``fk`` and its derivative at its coordinate value.

    Same pieces as :func:`~bodyfit.models.skeleton.functions.evaluate_table` (cubic pieces, sine, arc
    basis), differentiated by hand: ``g1' = cos x - sin x / x + (1 - cos x) / x^2`` and
    ``g2' = (x cos x - sin x) / x^2 + sin x``, with their Taylor series near 0.

    Args:
        x: (B, A) the coordinate value feeding each function.
    Returns:
        values and derivatives, (B, A) each.
    """
    xe = x.unsqueeze(-1)
    t = xe - fk.fn_anchor
    c = fk.fn_coef
    inside = ((xe >= fk.fn_lower) & (xe < fk.fn_upper)).to(x.dtype)
    f = (inside * (c[..., 0] + t * (c[..., 1] + t * (c[..., 2] + t * c[..., 3])))).sum(-1)
    df = (inside * (c[..., 1] + t * (2 * c[..., 2] + 3 * t * c[..., 3]))).sum(-1)
    amp, omega, phase = fk.fn_sine.unbind(-1)
    f = f + amp * torch.sin(omega * x + phase)
    df = df + amp * omega * torch.cos(omega * x + phase)
    small = torch.abs(x) < ARC_SMALL
    xs = torch.where(small, torch.ones_like(x), x)
    sin, cos = torch.sin(xs), torch.cos(xs)
    versine = 2 * torch.sin(xs / 2) ** 2
    g1 = torch.where(small, x / 2 - x**3 / 8, sin - versine / xs)
    g2 = torch.where(small, x**2 / 3 - x**4 / 30, (sin / xs - 1) + versine)
    d1 = torch.where(small, 0.5 - 3 * x**2 / 8, cos - sin / xs + versine / xs**2)
    d2 = torch.where(small, 2 * x / 3 - 2 * x**3 / 15, (xs * cos - sin) / xs**2 + sin)
    a, b = fk.fn_arc.unbind(-1)
    return f + a * g1 + b * g2, df + a * d1 + b * d2


def marker_jacobian(
    fk: SkeletonKinematics,
    chain: MarkerChain,
    local: torch.Tensor,
    q: torch.Tensor,
    root: torch.Tensor,
    scales: torch.Tensor,
    with_scales: bool = False,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Marker positions and their Jacobians with respect to ``[q, root]`` and (optionally) the scales.

    Positions are linear in the scale factors for a fixed pose (rotations do not depend on them; every
    offset and translation function is proportional to one segment's factor), which makes the scale
    Jacobian exact and cheap: per ancestor joint, the parent offset moves with the parent segment, the
    child offset with the child segment and the translation functions with the joint's scale segment.

    Args:
        local: (M, 3); q: (B, n_dof); root: (B, 3); scales: (B, n_seg, 3).
    Returns:
        positions (B, M, 3), Jacobian (B, M, 3, n_dof + 3) and, with ``with_scales``, the scale
        Jacobian (B, M, 3, n_seg, 3) (else None).
    """
    frames = fk(q, root, scales).frames
    x = body_points(frames, scales, chain.body, chain.segment, local)  # (B, M, 3)
    axes = _joint_axes(fk, q, root, scales, frames)
    jac_q = _coordinate_jacobian(chain, x, axes)
    if not with_scales:
        return x, jac_q, None
    return x, jac_q, _scale_jacobian(fk, chain, local, x, scales, frames, axes)


@dataclass(frozen=True)
class _JointAxes:
    """Every joint's transform axes at one pose (B frames, J joints).

    Attributes:
        df: (B, J, 6) derivative of each axis' function at its coordinate.
        d: (B, J, 3) translation function values (before scaling).
        Rp: (B, J, 3, 3) rotation of the parent frame (ground = identity).
        R_F: (B, J, 3, 3) rotation of the joint's F frame.
        moving_origin: (B, J, 3) origin o_M of the joint's moving frame.
        dirs: (B, J, 6, 3) world direction of each axis (3 rotation axes, then 3 scaled translations).
    """

    df: torch.Tensor
    d: torch.Tensor
    Rp: torch.Tensor
    R_F: torch.Tensor
    moving_origin: torch.Tensor
    dirs: torch.Tensor


def _joint_axes(
    fk: SkeletonKinematics, q: torch.Tensor, root: torch.Tensor, scales: torch.Tensor, frames: torch.Tensor
) -> _JointAxes:
    """The joint axes at ``q`` (B, n_dof), ``root`` (B, 3), ``scales`` (B, n_seg, 3) with body ``frames``
    (B, J, 4, 4)."""
    B = q.shape[0]
    J_n = len(fk.spec.joints)
    # Function values and derivatives of every transform axis (each depends on one input only).
    q_ext = torch.cat([q, root, q.new_zeros(B, 1)], dim=-1)[:, fk.cols]

    f, df = table_with_slope(q_ext, fk)
    f, df = f.reshape(B, J_n, 6), df.reshape(B, J_n, 6)
    theta, d = f[..., :3], f[..., 3:]

    padded = torch.cat([scales, scales.new_ones(B, 1, 3)], dim=1)
    s_p, s_f = padded[:, fk.p_seg], padded[:, fk.f_seg]
    mult = torch.einsum("jkc,bjc->bjk", fk.trans_scale_w, s_f) + fk.trans_unscaled  # (B, J, 3)
    p = torch.einsum("bjk,jkc->bjc", d * mult, fk.trans_axes)

    # Parent frame of every joint (ground = identity), then the joint's F frame and M origin.
    eye = torch.eye(4, dtype=q.dtype, device=q.device).expand(B, 1, 4, 4)
    parent = torch.as_tensor(fk.spec.body_parent_index, device=q.device)
    Xp = torch.cat([frames, eye], dim=1)[:, parent]  # index -1 -> identity
    Rp, tp = Xp[..., :3, :3], Xp[..., :3, 3]
    R_F = Rp @ fk.p_rot
    o_F = tp + (Rp @ (fk.p_trans * s_p).unsqueeze(-1)).squeeze(-1)
    o_M = o_F + (R_F @ p.unsqueeze(-1)).squeeze(-1)
    return _JointAxes(df, d, Rp, R_F, o_M, _world_directions(fk, R_F, theta, mult))


def _world_directions(
    fk: SkeletonKinematics, R_F: torch.Tensor, theta: torch.Tensor, mult: torch.Tensor
) -> torch.Tensor:
    """(B, J, 6, 3) world directions of every joint's axes: the rotation axes as the earlier rotations
    turn them, then the translation axes times their scale multipliers.

    Args:
        R_F: (B, J, 3, 3) the joints' F frames; theta: (B, J, 3) rotation angles; mult: (B, J, 3)
            translation scale multipliers.
    """
    Rk = axis_angle_matrix(fk.rot_axes, theta)  # (B, J, 3, 3, 3)
    a = fk.rot_axes  # (J, 3, 3): axis k of joint j
    R01 = Rk[:, :, 0] @ Rk[:, :, 1]
    w = torch.stack(
        [
            (R_F @ a[:, 0].unsqueeze(-1)).squeeze(-1),
            (R_F @ Rk[:, :, 0] @ a[:, 1].unsqueeze(-1)).squeeze(-1),
            (R_F @ R01 @ a[:, 2].unsqueeze(-1)).squeeze(-1),
        ],
        dim=2,
    )  # (B, J, 3, 3) world rotation axes
    tdir = torch.einsum("bjxy,bjky->bjkx", R_F, mult.unsqueeze(-1) * fk.trans_axes)  # (B, J, 3, 3)
    return torch.cat([w, tdir], dim=2)


def _coordinate_jacobian(chain: MarkerChain, x: torch.Tensor, axes: _JointAxes) -> torch.Tensor:
    """(B, M, 3, n_dof + 3) Jacobian of the marker positions ``x`` (B, M, 3) with respect to ``[q, root]``."""
    pm, pj, ps = chain.pair_marker, chain.pair_joint, chain.pair_slot
    direction = axes.dirs[:, pj, ps]  # (B, P, 3)
    lever = x[:, pm] - axes.moving_origin[:, pj]
    rot = torch.linalg.cross(direction, lever, dim=-1)
    contrib = torch.where((ps < 3).unsqueeze(-1), rot, direction) * axes.df[:, pj, ps].unsqueeze(-1)
    B, M, C = x.shape[0], x.shape[1], chain.n_columns
    jac = x.new_zeros(B, M * C, 3)
    jac.index_add_(1, pm * C + chain.pair_column, contrib)
    return jac.reshape(B, M, C, 3).transpose(-1, -2)


def _scale_jacobian(
    fk: SkeletonKinematics,
    chain: MarkerChain,
    local: torch.Tensor,
    x: torch.Tensor,
    scales: torch.Tensor,
    frames: torch.Tensor,
    axes: _JointAxes,
) -> torch.Tensor:
    """(B, M, 3, n_seg, 3) Jacobian of the marker positions ``x`` (B, M, 3) with respect to ``scales``
    (B, n_seg, 3): blocks (B, J, 3 [x], 3 [scale axis]) per ancestor joint and the marker's own term.

    Args:
        local: (M, 3) marker points before scaling; frames: (B, J, 4, 4) body frames.
    """
    B, M = x.shape[0], x.shape[1]
    n_seg = scales.shape[1]
    R_c = frames[..., :3, :3]
    block_p = axes.Rp * fk.p_trans.unsqueeze(-2)
    block_c = -R_c * fk.c_trans.unsqueeze(-2)
    block_f = axes.R_F @ torch.einsum("bjk,jka,jkx->bjxa", axes.d, fk.trans_scale_w, fk.trans_axes)
    am, aj = chain.anc_marker, chain.anc_joint
    S1 = n_seg + 1  # a last, discarded column takes the "no segment" (-1) entries
    jac_s = x.new_zeros(B, M * S1, 3, 3)

    def seg_index(seg: torch.Tensor) -> torch.Tensor:
        return torch.where(seg < 0, torch.full_like(seg, n_seg), seg)

    jac_s.index_add_(1, am * S1 + seg_index(fk.p_seg[aj]), block_p[:, aj])
    jac_s.index_add_(1, am * S1 + seg_index(fk.c_seg[aj]), block_c[:, aj])
    jac_s.index_add_(1, am * S1 + seg_index(fk.f_seg[aj]), block_f[:, aj])
    own = frames[:, chain.body, :3, :3] * local.unsqueeze(-2)  # (B, M, 3, 3)
    jac_s.index_add_(1, torch.arange(M) * S1 + chain.segment, own)
    return jac_s.reshape(B, M, S1, 3, 3)[:, :, :n_seg].permute(0, 1, 3, 2, 4)


ResidualFn = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]


@dataclass(frozen=True)
class SolveResult:
    """x: (B, P) solution; cost: (B,) half the squared residual norm; iterations: LM iterations run
    (the longest frame); evaluations: residual + Jacobian evaluations (per frame, summed over frames
    divided by B)."""

    x: torch.Tensor
    cost: torch.Tensor
    iterations: int
    evaluations: float


def levenberg_marquardt(
    residual: ResidualFn,
    x0: torch.Tensor,
    lower: torch.Tensor,
    upper: torch.Tensor,
    max_iterations: int = 50,
    rtol: float = 1e-4,
    step_tol: float = 1e-3,
) -> SolveResult:
    """Batched, box-constrained Levenberg-Marquardt: every row of ``x0`` is its own problem.

    The damping is Marquardt's, scaled by the diagonal of J^T J (Levenberg 1944; Marquardt 1963, see the
    module docstring). Bounds are kept by projection (D. P. Bertsekas, "Projected Newton methods for
    optimization problems with simple constraints", SIAM Journal on Control and Optimization 20(2), 1982):
    a variable on a bound whose gradient pushes outwards is held for the step, the others take the damped
    Gauss-Newton step, and the result is clipped into the box. Unlike a tanh reparameterisation
    (``Skeleton.from_unbounded``), a variable can leave a bound as soon as the data pull it inwards: through
    tanh the gradient vanishes at a limit, so a knee that reaches full extension at heel strike would stay
    stuck there.

    Args:
        residual: ``(x (b, P), rows (b,) long) -> (r (b, R), J (b, R, P))`` for the problems ``rows``.
        x0: (B, P) starting points inside the box.
        lower, upper: (P,) bounds (``-inf`` / ``inf`` for free variables).
        max_iterations: cap per problem.
        rtol: a problem stops when an accepted step lowers its cost by less than ``rtol`` (relative).
        step_tol: ... or when its step is shorter than this (x units: 1e-3 rad = 0.06 deg, 1 mm); the
            angles then agree with a 1e-7 tolerance to better than 0.01 deg on the OpenSim trials.
    Returns:
        :class:`SolveResult`.
    """
    B, P = x0.shape
    x = torch.maximum(torch.minimum(x0.clone(), upper), lower)
    all_rows = torch.arange(B, device=x0.device)
    r, J = residual(x, all_rows)
    cost = 0.5 * (r * r).sum(-1)
    lam = torch.full((B,), 1e-3, dtype=x0.dtype, device=x0.device)
    active = torch.ones(B, dtype=torch.bool, device=x0.device)
    eye = torch.eye(P, dtype=x0.dtype, device=x0.device)
    evaluations = float(B)
    iterations = 0
    for _ in range(max_iterations):
        rows = torch.nonzero(active).flatten()
        if rows.numel() == 0:
            break
        iterations += 1
        Ja, ra, xa = J[rows], r[rows], x[rows]
        H = Ja.transpose(1, 2) @ Ja
        g = (Ja.transpose(1, 2) @ ra.unsqueeze(-1)).squeeze(-1)
        held = ((xa <= lower) & (g > 0)) | ((xa >= upper) & (g < 0))  # (b, P)
        keep = (~held).to(x0.dtype)
        H = H * keep.unsqueeze(1) * keep.unsqueeze(2) + torch.diag_embed(1.0 - keep)
        g = g * keep
        diag = torch.diagonal(H, dim1=1, dim2=2).clamp_min(1e-9)
        A = H + lam[rows, None, None] * (torch.diag_embed(diag) + 1e-9 * eye)
        step = -torch.linalg.solve(A, g)
        x_new = torch.maximum(torch.minimum(xa + step, upper), lower)
        r_new, J_new = residual(x_new, rows)
        evaluations += rows.numel()
        cost_new = 0.5 * (r_new * r_new).sum(-1)
        ok = torch.isfinite(cost_new) & (cost_new <= cost[rows])
        gain = cost[rows] - cost_new
        acc = rows[ok]
        x[acc], r[acc], J[acc] = x_new[ok], r_new[ok], J_new[ok]
        small = (gain <= rtol * cost[rows]) | ((x_new - xa).norm(dim=-1) < step_tol)
        cost[acc] = cost_new[ok]
        lam[rows] = torch.where(ok, lam[rows] / 3.0, lam[rows] * 4.0).clamp(1e-9, 1e9)
        done = (ok & small) | (lam[rows] >= 1e9)
        active[rows[done]] = False
    return SolveResult(x, cost, iterations, evaluations / max(B, 1))


def fill_gaps(values: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Linear interpolation over rows that hold NaN (nearest valid row at the ends).

    Args:
        values: (T, D) with some all-NaN rows; times: (T,).
    Returns:
        (T, D); all-zero if no row is valid.
    """
    ok = np.isfinite(values).all(-1)
    if not ok.any():
        return np.zeros_like(values)
    return np.stack([np.interp(times, times[ok], values[ok, d]) for d in range(values.shape[1])], -1)

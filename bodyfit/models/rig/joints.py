"""One person's joint centres, solved from example poses of them as corrections to the segment scales.

P. Fechteler, A. Hilsmann and P. Eisert, "Example-based Body Model Optimization and Skinning", Eurographics
2016 Short Papers, section 4, solve each joint's location jointly with the examples' poses by Gauss-Newton.
Our skeleton is an OpenSim model (Rajagopal et al. 2016): its joints sit at fixed points of their parent
bodies, scaled per segment (x, y, z), and a joint moved anywhere else would no longer be that model. So the
person's joints are solved as offsets to the segment scales, as OpenSim's scale tool personalises a model
(Delp et al., "OpenSim: Open-Source Software to Create and Analyze Dynamic Simulations of Movement", IEEE
Transactions on Biomedical Engineering, 2007), bounded to ``limit`` of each scale.

The template stays where it is in the bind pose, so a scale offset moves the joints against the skin. At
fixed poses the bodies' origins, in the bind pose and in every example, are sums of rotated, scaled joint
offsets: linear in the scales, while their rotations do not depend on them, so the posed skin of linear
blend skinning is linear in the scale offsets. A joint that moves changes the pose that fits each example,
though, so as in the paper the scale offsets are solved together with every example's coordinates and root:
Gauss-Newton steps on

    min  sum_k c_kv |x_kv(d, q_k, r_k) - target_kv|^2 + ridge |d / s|^2 + pose_ridge |q_k - q_k,0|^2
    subject to |d| <= limit s and every coordinate within its range,

each a bounded linear least-squares problem (the Jacobian by finite differences, every column for all
examples in one batched forward pass), with ridges for the scales and coordinates the examples do not reach.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.optimize import lsq_linear

from bodyfit.models.body.model import BodyDecoder, BodyModel
from bodyfit.models.rig.subject import PersonalParts

STEP = 0.01
"""Scale offset (relative) of the finite differences: exact for linear blend skinning, whose skin is linear
in the scales; under swing-twist skinning, a linearisation about the current joints."""
POSE_STEP = 1e-4
"""Finite-difference step of the coordinates (radians or metres) and the root (metres)."""


@dataclass(frozen=True, kw_only=True)
class JointConfig:
    """limit: largest scale offset as a fraction of each scale; ridge: weight of |d / s|^2 and pose_ridge of
    |dq|^2 (per radian or metre) in m^2, against the data term (the mean over vertices and examples);
    stride: every how many vertices enter the solve; steps: Gauss-Newton steps."""

    limit: float = 0.15
    ridge: float = 1e-5
    pose_ridge: float = 1e-7
    stride: int = 8
    steps: int = 1


def skin_jacobian(
    model: BodyModel,
    personal: PersonalParts,
    shape: np.ndarray,
    poses: np.ndarray,
    roots: np.ndarray,
    vertices: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The person's posed skin (K, V', 3) and its derivatives in the segment scale offsets (K, V', 3, n_seg 3)
    and in each example's own coordinates and root (K, V', 3, n_dof + 3), for one shape (n_shape,), poses
    (K, n_dof), roots (K, 3) and template vertices ``vertices`` (V',), with the person's weights, template
    offsets and current scale offsets (``personal``).

    Every scale offset is one more bone coefficient of a decoder whose scale basis gains the identity (and
    whose template does not move with it); a coordinate column moves that coordinate in every example at
    once (each example's skin depends on its own pose only), so one batched forward pass gives every
    column."""
    base = np.asarray(model.data["scale_mean"], np.float64)
    n, nb, nq = base.size, model.n_bone, poses.shape[1]
    data = {
        **model.data,
        "scale_mean": base + personal.scale_offsets,
        "scale_basis": np.concatenate([model.data["scale_basis"], np.eye(n).reshape(n, *base.shape)]),
        "bone_correctives": np.concatenate(
            [model.data["bone_correctives"], np.zeros((n, model.n_vertices, 3))]
        ),
    }
    decoder = BodyDecoder(model.skeleton, data, torch.float64, model.skinning)
    decoder = decoder.with_weights(personal.weights).with_offsets(personal.offsets).restricted(vertices)
    K, m = len(poses), 1 + n + nq + 3
    steps = np.concatenate([STEP * np.where(base > 0, base, 1.0).ravel(), np.full(nq + 3, POSE_STEP)])
    c = np.zeros((m, K, nb + n + model.n_identity))
    c[:, :, :nb], c[:, :, nb + n :] = shape[:nb], shape[nb:]
    c[1 + np.arange(n), :, nb + np.arange(n)] = steps[:n, None]
    q, r = np.tile(poses, (m, 1, 1)), np.tile(roots, (m, 1, 1))
    q[1 + n + np.arange(nq), :, np.arange(nq)] += POSE_STEP
    r[1 + n + nq + np.arange(3), :, np.arange(3)] += POSE_STEP
    with torch.no_grad():
        out = decoder(
            torch.as_tensor(c.reshape(m * K, -1)),
            torch.as_tensor(q.reshape(m * K, -1)),
            torch.as_tensor(r.reshape(m * K, 3)),
        )[0]
    skin = out.double().numpy().reshape(m, K, len(vertices), 3)
    J = ((skin[1:] - skin[:1]) / steps[:, None, None, None]).transpose(1, 2, 3, 0)
    return skin[0], J[..., :n], J[..., n:]


def solve_joints(
    model: BodyModel,
    personal: PersonalParts,
    shape: np.ndarray,
    poses: np.ndarray,
    roots: np.ndarray,
    targets: np.ndarray,
    confidence: np.ndarray,
    config: JointConfig | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The person's segment scale offsets (n_seg, 3) and the examples' coordinates (K, n_dof) and roots
    (K, 3) that best explain them (module docstring), starting from ``personal``'s scale offsets and the
    given poses; ``targets`` (K, V, 3) and ``confidence`` (K, V) as the examples' fit weights them, the
    weights and template offsets those of ``personal``."""
    cfg = config or JointConfig()
    subset = np.arange(0, targets.shape[1], cfg.stride)
    c = confidence[:, subset]
    rows = np.sqrt(c / c.sum())[..., None]  # the data term is the mean over vertices and examples
    q, r = np.array(poses, np.float64), np.array(roots, np.float64)
    for _ in range(cfg.steps):
        at, Js, Jp = skin_jacobian(model, personal, shape, q, r, subset)
        step = _bounded_step(
            model,
            personal,
            q,
            (targets[:, subset] - at) * rows,
            Js * rows[..., None],
            Jp * rows[..., None],
            q - poses,
            cfg,
        )
        n = Js.shape[-1]
        scales = (personal.scale_offsets.ravel() + step[:n]).reshape(personal.scale_offsets.shape)
        personal = PersonalParts(personal.weights, personal.offsets, scales)
        moves = step[n:].reshape(len(q), -1)
        q, r = q + moves[:, : q.shape[1]], r + moves[:, q.shape[1] :]
    return personal.scale_offsets, q, r


def _bounded_step(
    model: BodyModel,
    personal: PersonalParts,
    q: np.ndarray,
    b: np.ndarray,
    Js: np.ndarray,
    Jp: np.ndarray,
    moved: np.ndarray,
    cfg: JointConfig,
) -> np.ndarray:
    """One Gauss-Newton step [d scales (n), then each example's d coordinates and d root (K (n_dof + 3))]
    for weighted residuals b (K, V', 3) and Jacobians Js (K, V', 3, n), Jp (K, V', 3, n_dof + 3), through
    the normal equations' Cholesky factor (their size is the unknowns', not the residuals'); ``moved``
    (K, n_dof): how far the coordinates have moved in this solve (the pose ridge pulls them back)."""
    K, n, p = len(q), Js.shape[-1], Jp.shape[-1]
    size = n + K * p
    N, g = np.zeros((size, size)), np.zeros(size)
    for k in range(K):
        js, jp = Js[k].reshape(-1, n), Jp[k].reshape(-1, p)
        bk = b[k].reshape(-1)
        sl = slice(n + k * p, n + (k + 1) * p)
        N[:n, :n] += js.T @ js
        N[:n, sl] = js.T @ jp
        N[sl, :n] = N[:n, sl].T
        N[sl, sl] = jp.T @ jp
        g[:n] += js.T @ bk
        g[sl] = jp.T @ bk
    scale = np.abs(np.asarray(model.data["scale_mean"], np.float64)).ravel()
    d0 = personal.scale_offsets.ravel()
    ridge = np.concatenate([cfg.ridge / scale**2, np.full(K * p, cfg.pose_ridge)])
    prior = np.concatenate(
        [cfg.ridge * d0 / scale**2, np.pad(moved, ((0, 0), (0, 3))).ravel() * cfg.pose_ridge]
    )
    R = np.linalg.cholesky(N + np.diag(ridge)).T
    rhs = np.linalg.solve(R.T, g - prior)
    lo_q, hi_q = model.skeleton.ranges[:, 0] - q, model.skeleton.ranges[:, 1] - q
    free = np.full((K, 3), np.inf)
    lo = np.concatenate([-cfg.limit * scale - d0, np.concatenate([lo_q, -free], 1).ravel()])
    hi = np.concatenate([cfg.limit * scale - d0, np.concatenate([hi_q, free], 1).ravel()])
    return lsq_linear(R, rhs, bounds=(np.minimum(lo, 0.0), np.maximum(hi, 0.0)), method="bvls").x

"""L-BFGS for many independent problems at once (one per row), for batched fitting.

L-BFGS: D. C. Liu and J. Nocedal, "On the limited memory BFGS method for large scale optimization",
Mathematical Programming 45, 1989; the two-loop recursion is algorithm 7.4 of J. Nocedal and S. J. Wright,
"Numerical Optimization", Springer, 2nd ed., 2006; the sufficient-decrease test is that of L. Armijo,
"Minimization of functions having Lipschitz continuous first partial derivatives", Pacific Journal of
Mathematics 16(1), 1966.

torch's L-BFGS treats a batch as one problem: one step length and one curvature history for all meshes, so
an easy mesh waits for a hard one and a hard one drags the history of the others. Here every row has its
own history, its own step length and its own Armijo test, and each iteration costs exactly one batched
evaluation of the losses and their gradients: a row whose trial point fails the test keeps its point and
tries a shorter step at the next iteration.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

ARMIJO = 1e-4
BACKTRACK = 0.3
CURVATURE_EPS = 1e-10


@dataclass(frozen=True)
class LbfgsResult:
    """z: (N, P) final points; loss: (N,) final losses; evaluations: batched evaluations used."""

    z: torch.Tensor
    loss: torch.Tensor
    evaluations: int


def _value_and_grad(
    f: Callable[[torch.Tensor], torch.Tensor], z: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    z = z.detach().requires_grad_(True)
    loss = f(z)
    (grad,) = torch.autograd.grad(loss.sum(), z)
    return loss.detach(), grad


def batched_lbfgs(
    f: Callable[[torch.Tensor], torch.Tensor],
    z0: torch.Tensor,
    iterations: int,
    history: int = 10,
    newton_start: bool = False,
) -> LbfgsResult:
    """Minimise N independent problems.

    Args:
        f: (N, P) points -> (N,) losses; row n's loss may depend on row n only.
        z0: (N, P) start points.
        iterations: batched evaluations to spend (one per iteration).
        history: curvature pairs kept per row.
        newton_start: the first step is -gradient (the variables are scaled so that the Hessian is about
            the identity); default: a step of unit length along it.
    Returns:
        :class:`LbfgsResult`.
    """
    N, P = z0.shape
    z = z0.detach().clone()
    loss, g = _value_and_grad(f, z)
    S = torch.zeros(history, N, P, dtype=z.dtype)
    Y = torch.zeros(history, N, P, dtype=z.dtype)
    rho = torch.zeros(history, N, dtype=z.dtype)
    gamma = torch.ones(N, dtype=z.dtype) if newton_start else 1.0 / g.norm(dim=1).clamp_min(1e-12)
    step = torch.ones(N, dtype=z.dtype)
    slot = 0
    for it in range(iterations):
        # Two-loop recursion over the pairs recorded so far, newest first; skipped pairs have rho = 0 and
        # do nothing.
        q = g.clone()
        alpha = torch.zeros(history, N, dtype=z.dtype)
        order = [(slot - 1 - k) % history for k in range(min(it, history))]
        for i in order:
            alpha[i] = rho[i] * (S[i] * q).sum(1)
            q -= alpha[i, :, None] * Y[i]
        r = gamma[:, None] * q
        for i in reversed(order):
            beta = rho[i] * (Y[i] * r).sum(1)
            r += S[i] * (alpha[i] - beta)[:, None]
        d = -r
        slope = (g * d).sum(1)
        uphill = slope >= 0  # lost positive definiteness: fall back to steepest descent
        d[uphill] = -gamma[uphill, None] * g[uphill]
        slope = (g * d).sum(1)
        trial = z + step[:, None] * d
        t_loss, t_grad = _value_and_grad(f, trial)
        ok = torch.isfinite(t_loss) & (t_loss <= loss + ARMIJO * step * slope)
        # Accepted rows move and record a curvature pair; the others shorten their step.
        s_k = torch.where(ok[:, None], trial - z, torch.zeros_like(z))
        y_k = torch.where(ok[:, None], t_grad - g, torch.zeros_like(z))
        sy = (s_k * y_k).sum(1)
        good = ok & (sy > CURVATURE_EPS)
        S[slot], Y[slot] = s_k, y_k
        rho[slot] = torch.where(good, 1.0 / sy.clamp_min(CURVATURE_EPS), torch.zeros_like(sy))
        gamma = torch.where(good, sy / (y_k * y_k).sum(1).clamp_min(1e-30), gamma)
        slot = (slot + 1) % history
        z = torch.where(ok[:, None], trial, z)
        loss = torch.where(ok, t_loss, loss)
        g = torch.where(ok[:, None], t_grad, g)
        step = torch.where(ok, torch.ones_like(step), step * BACKTRACK)
    return LbfgsResult(z, loss, iterations + 1)

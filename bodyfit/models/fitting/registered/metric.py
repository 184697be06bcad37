"""The geometry of a registered fit's variables: the diagonal preconditioner (:func:`unit_scales`), the
Jacobian of the vertices in a stage's variables (:func:`stage_jacobian`) and the Gauss-Newton metric built
from it (:func:`gauss_newton_metric`, Nocedal and Wright, "Numerical Optimization", Springer, 2nd ed. 2006,
section 10.3), in which a stage's L-BFGS can run.

A stage's variables are the preconditioned unbounded coordinates ``u`` of its free DOFs (BLSM's tanh
mapping, Wang, Güler, Kokkinos, Papandreou, Zafeiriou, "BLSM: A Bone-Level Skinned Model of the Human
Mesh", ECCV 2020, eq. 6), the root (3) and its free shape coefficients, in that order
(:meth:`.fitter.RegisteredFitter.optimise`).
"""

from __future__ import annotations

import numpy as np
import torch

from bodyfit.models.body.model import BodyDecoder
from bodyfit.models.skeleton.model import Skeleton

Scales = tuple[torch.Tensor, torch.Tensor, torch.Tensor]
"""Per-parameter units: u (n_dof,), root (3,), shape (n_shape,)."""
State = tuple[torch.Tensor, torch.Tensor, torch.Tensor]
"""A fit's preconditioned variables (u (B, n_dof), root (B, 3), shape (B or 1, n_shape)): the parameters
divided by :data:`Scales` (:meth:`.fitter.RegisteredFitter.start_state`)."""


def unit_scales(
    skeleton: Skeleton, decoder: BodyDecoder, bind_coordinates: np.ndarray, n_shape: int, dtype: torch.dtype
) -> Scales:
    """Per-parameter units in which one unit moves ``decoder``'s vertices by about 1 mm RMS, from the
    Jacobian at the mean body in the bind pose ``bind_coordinates`` (n_dof,). L-BFGS (Liu and Nocedal, "On
    the limited memory BFGS method for large scale optimization", Mathematical Programming, 1989) starts
    from a scalar Hessian guess; without these units the pelvis (moving every vertex) and a wrist (moving a
    few) differ in curvature by orders of magnitude and it converges slowly."""
    skel = skeleton
    q = skel.inside(bind_coordinates, 0.1)
    n_dof, ns = skel.n_dof, n_shape
    p0 = torch.cat([
        skel.to_unbounded(torch.as_tensor(q[None], dtype=dtype)), torch.zeros(1, 3 + ns, dtype=dtype)
    ], dim=1)  # fmt: skip

    def f(p: torch.Tensor) -> torch.Tensor:
        u, r, c = p[:, :n_dof], p[:, n_dof : n_dof + 3], p[:, n_dof + 3 :]
        return decoder(c, skel.from_unbounded(u), r)[0] * 1000.0

    # Rows are independent, so P copies of p0 give every column at once (row k along parameter k), as
    # Jacobian-vector products by two reverse passes: g(w) = J^T w is linear in w, and its own
    # vector-Jacobian product with e_k is J e_k. (torch's forward mode imports its compiler: 1 s more.)
    P = p0.shape[1]
    with torch.enable_grad():
        x = p0.repeat(P, 1).requires_grad_()
        y = f(x)
        v = torch.zeros_like(y, requires_grad=True)
        (g,) = torch.autograd.grad(y, x, v, create_graph=True)
        (cols,) = torch.autograd.grad(g, v, torch.eye(P, dtype=dtype))
    rms = cols.reshape(P, -1, 3).norm(dim=-1).pow(2).mean(-1).sqrt().clamp_min(1e-3)  # (P,) mm per unit
    scale = 1.0 / rms
    return scale[:n_dof], scale[n_dof : n_dof + 3], scale[n_dof + 3 :]


def stage_jacobian(
    decoder: BodyDecoder,
    skeleton: Skeleton,
    scales: Scales,
    free: tuple[torch.Tensor, torch.Tensor],
    z: State,
    step: float = 0.05,
) -> torch.Tensor:
    """(B, V' * 3, P) d vertices (mm) / d a stage's variables (one problem per mesh), by forward
    differences of ``step`` units, on ``decoder``'s vertices (V'). free: the stage's free coordinates and
    shape coefficients (their indices, :meth:`.fitter.RegisteredFitter.free_variables`)."""
    z_u, z_r, z_c = z
    s_u, s_r, s_c = scales
    B = z_u.shape[0]
    fd, fs = free
    P = len(fd) + 3 + len(fs)
    Z0 = torch.cat([z_u[:, fd], z_r, z_c[:, fs].expand(B, -1)], 1)
    Z = Z0[:, None].repeat(1, P + 1, 1)
    Z[:, 1:] += step * torch.eye(P, dtype=Z.dtype)
    Z = Z.reshape(B * (P + 1), P)
    u = z_u.repeat_interleave(P + 1, 0).index_copy(1, fd, Z[:, : len(fd)])
    c = z_c.expand(B, -1).repeat_interleave(P + 1, 0).index_copy(1, fs, Z[:, len(fd) + 3 :])
    with torch.no_grad():
        q = skeleton.from_unbounded(u * s_u)
        v = decoder(c * s_c, q, Z[:, len(fd) : len(fd) + 3] * s_r)[0] * 1000.0
    v = v.reshape(B, P + 1, -1)
    return ((v[:, 1:] - v[:, :1]) / step).mT


def gauss_newton_metric(
    jacobian: torch.Tensor,
    shape_scales: torch.Tensor,
    problems: int,
    shape_prior: float,
    normals: np.ndarray | None = None,
    tangential: float = 1.0,
    regularise: float = 1e-3,
) -> torch.Tensor:
    """(problems, P', P') float64 Gauss-Newton metric of a vertex-to-surface loss with the shape prior
    ``shape_prior |c|^2``, in a stage's variables (one problem per mesh, or one for the batch when the shape
    is shared, then P' = B / problems * pose variables + shape variables):

        sum over the problem's meshes of 2 mean_v J_v^T N_v J_v, + the shape prior's Hessian
        + regularise * mean(diag) I,

    J_v (3, P) the rows of vertex v of ``jacobian`` (B, V' * 3, P) (:func:`stage_jacobian`);
    N_v = n n^T + tangential (I - n n^T) for normals (B, V', 3), the identity without them. shape_scales:
    (n_free_shape,) the units of the stage's free shape coefficients, which come last in its variables."""
    J = jacobian.double()
    B, _, P = J.shape
    J = J.reshape(B, -1, 3, P)
    M = tangential * torch.einsum("bvkp,bvkq->bpq", J, J)
    if normals is not None:
        Jn = torch.einsum("bvk,bvkp->bvp", torch.as_tensor(normals, dtype=J.dtype), J)
        M += (1.0 - tangential) * Jn.mT @ Jn
    M *= 2.0 / J.shape[1]
    n_shape = len(shape_scales)
    M = shared_layout(M, n_shape, problems)
    n = M.shape[-1]
    if n_shape:  # the shape's variables come last
        s_c = shape_scales.double()
        M[:, n - n_shape :, n - n_shape :] += torch.diag(2.0 * shape_prior * s_c**2)
    M += regularise * M.diagonal(dim1=1, dim2=2).mean(1)[:, None, None] * torch.eye(n, dtype=M.dtype)
    return M


def shared_layout(M: torch.Tensor, n_shape: int, problems: int) -> torch.Tensor:
    """Per-mesh metrics M (B, P, P), the last ``n_shape`` variables the shape's, as ``problems`` metrics in
    :meth:`.fitter.RegisteredFitter.optimise`'s layout: unchanged for one problem per mesh; for a shared
    shape, each problem's meshes' pose blocks on the diagonal, their couplings to the shape, and the shape's
    block summed."""
    B, P, _ = M.shape
    if problems == B:
        return M
    m = B // problems
    p = P - n_shape
    blocks = M.reshape(problems, m, P, P)
    out = torch.zeros(problems, m * p + n_shape, m * p + n_shape, dtype=M.dtype)
    for k in range(m):
        rows = slice(k * p, (k + 1) * p)
        out[:, rows, rows] = blocks[:, k, :p, :p]
        out[:, rows, m * p :] = blocks[:, k, :p, p:]
        out[:, m * p :, rows] = blocks[:, k, p:, :p]
    out[:, m * p :, m * p :] = blocks[:, :, p:, p:].sum(1)
    return out

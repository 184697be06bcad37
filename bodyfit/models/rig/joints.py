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
offsets: linear in the scales, while their rotations do not depend on them. The posed skin of linear blend
skinning is then linear in the scale offsets, and the step of the alternation is one bounded linear
least-squares problem over every example (the Gauss-Newton step, exact here), with a ridge toward zero for
the scales the poses do not reach:

    min_{|d| <= limit s}  sum_k c_kv |x_kv(d) - target_kv|^2 + ridge |d / s|^2

The poses are refitted after it (the alternation of :mod:`.build`).
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


@dataclass(frozen=True, kw_only=True)
class JointConfig:
    """limit: largest scale offset as a fraction of each scale; ridge: weight of |d / s|^2 in m^2 (against
    the data term, mean over vertices and examples); stride: every how many vertices enter the solve."""

    limit: float = 0.15
    ridge: float = 1e-5
    stride: int = 6


def scale_jacobian(
    model: BodyModel,
    personal: PersonalParts,
    shape: np.ndarray,
    poses: np.ndarray,
    roots: np.ndarray,
    vertices: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The person's posed skin (K, V', 3) and its derivative (K, V', 3, n_seg 3) in the segment scale
    offsets, for one shape (n_shape,), poses (K, n_dof), roots (K, 3) and template vertices ``vertices``
    (V',), with the person's weights, template offsets and current scale offsets (``personal``).

    Every scale offset is one more bone coefficient of a decoder whose scale basis gains the identity (and
    whose template does not move with it), so one batched forward pass gives all the finite differences."""
    base = np.asarray(model.data["scale_mean"], np.float64)
    n, nb = base.size, model.n_bone
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
    K = len(poses)
    steps = STEP * np.where(base > 0, base, 1.0).ravel()
    c = np.zeros((n + 1, K, nb + n + model.n_identity))
    c[:, :, :nb], c[:, :, nb + n :] = shape[:nb], shape[nb:]
    c[1 + np.arange(n), :, nb + np.arange(n)] = steps[:, None]
    with torch.no_grad():
        out = decoder(
            torch.as_tensor(c.reshape(-1, c.shape[-1])),
            torch.as_tensor(np.tile(poses, (n + 1, 1))),
            torch.as_tensor(np.tile(roots, (n + 1, 1))),
        )[0]
    skin = out.double().numpy().reshape(n + 1, K, len(vertices), 3)
    J = (skin[1:] - skin[:1]) / steps[:, None, None, None]
    return skin[0], J.transpose(1, 2, 3, 0)


def solve_scale_offsets(
    model: BodyModel,
    personal: PersonalParts,
    shape: np.ndarray,
    poses: np.ndarray,
    roots: np.ndarray,
    targets: np.ndarray,
    confidence: np.ndarray,
    config: JointConfig | None = None,
) -> np.ndarray:
    """The person's segment scale offsets (n_seg, 3) that best explain the examples (module docstring),
    starting from ``personal``'s; ``targets`` (K, V, 3) and ``confidence`` (K, V) as the examples' fit
    weights them, the poses (K, n_dof) and roots (K, 3) fixed, the weights and template offsets those of
    ``personal``."""
    cfg = config or JointConfig()
    base = np.asarray(model.data["scale_mean"], np.float64)
    subset = np.arange(0, targets.shape[1], cfg.stride)
    at, J = scale_jacobian(model, personal, shape, poses, roots, subset)
    c = confidence[:, subset]
    rows = np.sqrt(c / c.sum())[..., None]  # the mean over vertices and examples
    A = (J * rows[..., None]).reshape(-1, base.size)
    b = ((targets[:, subset] - at) * rows).reshape(-1)
    scale = np.abs(base).ravel()
    d0 = personal.scale_offsets.ravel()
    # ridge |(d0 + step) / s|^2 as rows: sqrt(ridge) / s * step = -sqrt(ridge) / s * d0
    ridge = np.sqrt(cfg.ridge) / scale
    # The same least squares through the normal equations' Cholesky factor: n_seg 3 rows, not K V' 3.
    N = A.T @ A + np.diag(ridge**2)
    R = np.linalg.cholesky(N).T
    rhs = np.linalg.solve(R.T, A.T @ b - ridge**2 * d0)
    lo, hi = -cfg.limit * scale - d0, cfg.limit * scale - d0
    step = lsq_linear(R, rhs, bounds=(lo, hi), method="bvls").x
    return (d0 + step).reshape(base.shape)

"""Rest-pose offsets: one person's surface detail beyond the shape space, fitted on posed frames of them.

A linear shape space of a few dozen coefficients cannot follow every body: hands, feet and faces of other
templates are shaped differently. As in SMPL+D (Alldieck, Magnor, Xu, Theobalt, Pons-Moll, "Video Based
Reconstruction of 3D People Models", CVPR 2018), per-vertex offsets D (V, 3) are added to the person's
template before skinning, so they move with the body; they play the part of BLiSS's refinement beyond its
linear shape space (Muralikrishnan, Huang, Ceylan, Mitra, "BLiSS: Bootstrapped Linear Shape Space", 3DV 2024,
section 3.3), linear here and solved in closed form. A posed vertex becomes ``v + A_v D_v`` with
``A_v = sum_j w_vj R_j R_bind,j^T`` (:meth:`~bodyfit.models.body.model.BodyDecoder.blended_rotations`).
Fitted on K posed frames of the same person with residuals ``r = target - fitted vertex``:

    sum_k sum_v w_kv |A_kv D_v - r_kv|^2 + smoothness |L D|^2 + stiffness |D|^2      (L: mesh Laplacian)

The blended rotations are close to orthonormal (exactly so on rigid parts), so the data term is taken as
``w_kv |D_v - A_kv^T r_kv|^2``, which leaves one sparse system per axis
(:func:`~bodyfit.models.fitting.common.nonrigid.solve_offsets`). Where no frame has data (weight 0) the
offsets follow their neighbours and fade to zero. Offsets never move the skeleton: joints and bone scales stay
those of the shape coefficients.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
import torch

from bodyfit.models.errors import ShapeError
from bodyfit.models.fitting.common.nonrigid import solve_offsets
from bodyfit.models.fitting.common.surface import laplacian
from bodyfit.models.fitting.registered.stages import check_at_least

if TYPE_CHECKING:
    from bodyfit.models.body.model import BodyDecoder
    from bodyfit.models.fitting.registered.fitter import BodyFit


@dataclass(frozen=True, kw_only=True)
class OffsetConfig:
    """smoothness, stiffness: weights of |L D|^2 and |D|^2 against a data weight of one per vertex and
    frame; max_residual: residuals longer than this (m) are left out (not this body's surface).

    Raises:
        ValueError: a negative weight or a residual limit that is not positive (the message names the field).
    """

    smoothness: float = 1.0
    stiffness: float = 0.02
    max_residual: float = 0.08

    def __post_init__(self) -> None:
        check_at_least("OffsetConfig", "smoothness", self.smoothness, 0.0)
        check_at_least("OffsetConfig", "stiffness", self.stiffness, 0.0)
        if not self.max_residual > 0:
            raise ValueError(f"OffsetConfig.max_residual must be positive; got {self.max_residual!r}")


def fit_rest_offsets(
    rotations: np.ndarray,
    residuals: np.ndarray,
    weights: np.ndarray,
    faces: np.ndarray,
    config: OffsetConfig | None = None,
) -> np.ndarray:
    """Rest-pose offsets (V, 3) explaining the residuals of K posed fits of one person (module docstring).

    Args:
        rotations: (K, V, 3, 3) blended skinning rotations of the fitted frames; residuals: (K, V, 3) target
            minus fitted vertex, metres, in the same frame; weights: (K, V) per-vertex confidence (0 =
            missing); faces: (F, 3) the template's triangles.
    Returns:
        (V, 3) float64 metres.
    """
    cfg = config or OffsetConfig()
    K, V = residuals.shape[:2]
    if rotations.shape != (K, V, 3, 3) or weights.shape != (K, V):
        raise ShapeError(
            f"offsets need rotations (K, V, 3, 3), residuals (K, V, 3) and weights (K, V) of the same K, V; "
            f"got {rotations.shape}, {residuals.shape}, {weights.shape}"
        )
    w = np.where(np.linalg.norm(residuals, axis=-1) < cfg.max_residual, weights, 0.0)
    rest = np.einsum("kvji,kvj->kvi", rotations, residuals)  # A^T r: each residual in the rest pose
    a = w.sum(0) / K
    rhs = np.einsum("kv,kvi->vi", w, rest) / K
    L = laplacian(faces, V)
    regulariser = (cfg.smoothness * (L.T @ L) + cfg.stiffness * sp.identity(V)).tocsr()
    return solve_offsets(a, rhs, regulariser)


def offsets_of_fit(
    decoder: BodyDecoder,
    fit: BodyFit,
    targets: np.ndarray,
    weights: np.ndarray,
    faces: np.ndarray,
    config: OffsetConfig | None = None,
) -> np.ndarray:
    """Rest-pose offsets (V, 3) for what ``fit`` (K poses of one person, made with ``decoder``) leaves of
    ``targets`` (K, V, 3) with weights (K, V) (:func:`fit_rest_offsets`, with the skin's blended rotations
    at the fitted poses). Offsets already in ``decoder`` do not change the rotations: the result adds to
    them."""
    dtype = decoder.bind_rot_t.dtype
    with torch.no_grad():
        shape, q, root = (torch.as_tensor(a, dtype=dtype) for a in (fit.shape, fit.coordinates, fit.root))
        _, _, frames, _ = decoder(shape, q, root)
    rotations = decoder.blended_rotations(frames, q)
    return fit_rest_offsets(rotations, targets - fit.vertices, weights, faces, config)

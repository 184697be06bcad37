"""The body decoder with the spiral identity term, in torch and ONNX.

The skeleton, the bone-corrected template and the skinning are the linear model's (:class:`BodyDecoder`
built without its identity PCA), so the skeleton follows the bone coefficients exactly as it does there;
only the identity offsets, added to the template in the bind pose before skinning, come from the spiral
decoder (BLSM eq. 1, 11, 12: H. Wang, R. A. Güler, I. Kokkinos, G. Papandreou and S. Zafeiriou, "BLSM: A
Bone-Level Skinned Model of the Human Mesh", European Conference on Computer Vision (ECCV), 2020).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

from bodyfit.models.body.lbs import blend_block, blend_rows
from bodyfit.models.body.model import BodyDecoder, SkinBlock
from bodyfit.models.decoders.spiral import SpiralDecoder, dense
from bodyfit.models.skeleton.model import Skeleton
from bodyfit.models.skeleton.onnx_export import export_module

INPUTS = ("shape", "coordinates", "root")
OUTPUTS = ("vertices", "joints")


def bone_only_decoder(skeleton: Skeleton, data: dict[str, np.ndarray], dtype: torch.dtype) -> BodyDecoder:
    """The linear body decoder of ``data`` (body.npz arrays) with no identity components: shape = c_b."""
    V = data["vertices_mean"].shape[0]
    return BodyDecoder(skeleton, {**data, "identity_basis": np.zeros((0, V, 3))}, dtype)


class SpiralBody(nn.Module):
    """(shape (B, n_bone + d), coordinates (B, n_dof), root (B, 3)) -> vertices (B, V, 3), joints (B, J, 3).

    shape = [bone coefficients, identity code]; the identity code is in standard deviations of the
    training bodies' codes (z = latent_mean + code * latent_std), like the linear model's coefficients.
    """

    latent_mean: torch.Tensor
    latent_std: torch.Tensor

    def __init__(
        self, body: BodyDecoder, spiral: SpiralDecoder, latent_mean: np.ndarray, latent_std: np.ndarray
    ) -> None:
        super().__init__()
        self.body, self.spiral = body, spiral
        self.n_bone = body.n_bone
        self.register_buffer("latent_mean", torch.as_tensor(latent_mean, dtype=torch.float32))
        self.register_buffer("latent_std", torch.as_tensor(latent_std, dtype=torch.float32))
        self.blocks = [b for b in body.skin.children() if isinstance(b, SkinBlock)]
        self.block_sizes = [int(b.weights_t.shape[1]) for b in self.blocks]

    def offsets(self, code: torch.Tensor) -> torch.Tensor:
        """Identity offsets (B, V, 3) of codes (B, d) in standard deviations."""
        return self.spiral(self.latent_mean + code.float() * self.latent_std)

    def forward(
        self, shape: torch.Tensor, q: torch.Tensor, root: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        body = self.body
        B = shape.shape[0]
        rest_offsets = self.offsets(shape[:, self.n_bone :]).to(shape.dtype).transpose(1, 2)  # (B, 3, V)
        scales, coeffs = body._shape_terms(shape[:, : self.n_bone])
        world = body.fk.frames_cm(q, root, scales)
        rotations, translations = blend_rows(body._transforms(world, body._bind_shift(coeffs)))
        parts, start = [], 0
        for block, size in zip(self.blocks, self.block_sizes, strict=True):
            rest = (coeffs @ block.basis).reshape(B, 3, size) + rest_offsets[:, :, start : start + size]
            parts.append(blend_block(rest, block.weights_t, rotations[:, block.bodies],
                                     translations[:, block.bodies]))  # fmt: skip
            start += size
        frames = world.permute(3, 2, 0, 1)
        return torch.cat(parts, dim=1), body.joints(frames, scales)


def export_spiral_onnx(model: SpiralBody, path: str | Path | None = None) -> bytes:
    """Export :class:`SpiralBody` (float32, dynamic batch): inputs shape (B, n_bone + d), coordinates
    (B, n_dof), root (B, 3); outputs vertices (B, V, 3) and joints (B, J, 3). Returns the model bytes (also
    written to ``path`` when given)."""
    dense(model)
    args = (
        torch.zeros(2, model.n_bone + model.spiral.d),
        torch.zeros(2, model.body.fk.n_dof),
        torch.zeros(2, 3),
    )
    return export_module(model, args, INPUTS, OUTPUTS, path)

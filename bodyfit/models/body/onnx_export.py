"""Export the body model's forward (parameters -> skin vertices and joints) to ONNX, dynamic batch."""

from __future__ import annotations

from pathlib import Path

import torch

from bodyfit.models.body.model import BodyDecoder
from bodyfit.models.skeleton.onnx_export import export_module

BODY_ONNX = "body.onnx"
INPUTS = ("shape", "coordinates", "root")
OUTPUTS = ("vertices", "joints")


class _SkinAndJoints(torch.nn.Module):
    def __init__(self, decoder: BodyDecoder) -> None:
        super().__init__()
        self.decoder = decoder

    def forward(
        self, shape: torch.Tensor, q: torch.Tensor, root: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        vertices, joints, _, _ = self.decoder(shape, q, root)
        return vertices, joints


def export_body_onnx(decoder: BodyDecoder, n_shape: int, path: str | Path | None = None) -> bytes:
    """Inputs shape (B, n_shape), coordinates (B, n_dof), root (B, 3); outputs vertices (B, V, 3) and
    joints (B, J, 3). Returns the model bytes (also written to ``path`` when given)."""
    dtype = decoder.bind_rot_t.dtype
    args = (
        torch.zeros(2, n_shape, dtype=dtype),
        torch.zeros(2, decoder.fk.n_dof, dtype=dtype),
        torch.zeros(2, 3, dtype=dtype),
    )
    return export_module(_SkinAndJoints(decoder), args, INPUTS, OUTPUTS, path)

"""Export the skeleton's forward kinematics to ONNX (dynamic batch)."""

from __future__ import annotations

import logging
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import torch

from bodyfit.models.skeleton.kinematics import SkeletonKinematics

INPUTS = ("coordinates", "root", "scales")
OUTPUTS = ("frames", "joint_centres")


class _FullInputs(torch.nn.Module):
    """Wraps the FK so that root and scales are required inputs (ONNX graphs have fixed signatures)."""

    def __init__(self, fk: SkeletonKinematics) -> None:
        super().__init__()
        self.fk = fk

    def forward(
        self, q: torch.Tensor, root: torch.Tensor, scales: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        pose = self.fk(q, root, scales)
        return pose.frames, pose.joint_centres


def export_module(
    module: torch.nn.Module,
    args: tuple[torch.Tensor, ...],
    inputs: tuple[str, ...],
    outputs: tuple[str, ...],
    path: str | Path | None = None,
    opset: int = 18,
) -> bytes:
    """Export ``module`` with the dynamo exporter, axis 0 of every input a dynamic batch. Returns the model
    bytes (also written to ``path`` when given). The exporter's notices (operators of packages we do not
    use, its own deprecations) are kept off the user's terminal; its errors still raise."""
    batch = torch.export.Dim("batch", min=1)
    with _quiet_exporter():
        program = torch.onnx.export(
            module.eval(),
            args,
            input_names=list(inputs),
            output_names=list(outputs),
            dynamic_shapes=tuple({0: batch} for _ in args),
            opset_version=opset,
            dynamo=True,
            verbose=False,
        )
    assert program is not None
    data: bytes = program.model_proto.SerializeToString()
    if path is not None:
        Path(path).write_bytes(data)
    return data


@contextmanager
def _quiet_exporter() -> Iterator[None]:
    """Silence the ONNX exporter's warnings and log lines below ERROR for the duration, then restore."""
    logger = logging.getLogger("torch.onnx")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", category=UserWarning)
            warnings.simplefilter("ignore", category=FutureWarning)
            yield
    finally:
        logger.setLevel(level)


def export_fk_onnx(fk: SkeletonKinematics, path: str | Path | None = None, opset: int = 18) -> bytes:
    """Export ``fk`` to ONNX: inputs coordinates (B, n_dof), root (B, 3), scales (B, n_seg, 3); outputs
    frames (B, n_body, 4, 4) and joint_centres (B, n_joint, 3). Returns the model bytes (also written to
    ``path`` when given)."""
    dtype = fk.p_trans.dtype
    B = 2
    args = (
        torch.zeros(B, fk.n_dof, dtype=dtype),
        torch.zeros(B, 3, dtype=dtype),
        torch.ones(B, fk.n_seg, 3, dtype=dtype),
    )
    return export_module(_FullInputs(fk), args, INPUTS, OUTPUTS, path, opset)

"""The skeleton (bone) mesh: Rajagopal2015's bone geometry attached to our bodies, posed and scaled.

Built once from the ``Geometry/*.vtp.ply`` files inside the nimblephysics wheel (``build_bone_mesh``) and
stored as ``assets/bones.npz``: vertices in their body's frame, triangles, and each vertex's body. Posing
(``pose_bones``) scales each vertex by its body's segment factors (as OpenSim scales attached meshes), then
applies the body frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from bodyfit.models.assets import verified_asset
from bodyfit.models.errors import AssetError, ShapeError
from bodyfit.models.skeleton.spec import SkeletonSpec

BONES_ASSET = "bones.npz"


def read_vtk_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a binary little-endian PLY written by VTK (float xyz; polygon faces, fan-triangulated).

    Args:
        path: the .ply file.
    Returns:
        vertices (V, 3) float64, triangles (F, 3) int64.
    """
    raw = path.read_bytes()
    end = raw.find(b"end_header\n")
    if end < 0 or b"binary_little_endian" not in raw[:end]:
        raise AssetError(f"{path} is not a binary little-endian PLY file")
    header = raw[:end].decode("ascii").split()
    nv = int(header[header.index("vertex") + 1])
    nf = int(header[header.index("face") + 1])
    pos = end + len(b"end_header\n")
    verts = np.frombuffer(raw, dtype="<f4", count=3 * nv, offset=pos).reshape(nv, 3).astype(np.float64)
    pos += 12 * nv
    tris: list[tuple[int, int, int]] = []
    for _ in range(nf):
        n = raw[pos]
        idx = np.frombuffer(raw, dtype="<i4", count=n, offset=pos + 1)
        pos += 1 + 4 * n
        tris.extend((int(idx[0]), int(idx[k]), int(idx[k + 1])) for k in range(1, n - 1))
    return verts, np.array(tris, dtype=np.int64).reshape(-1, 3)


def build_bone_mesh(spec: SkeletonSpec, geometry_dir: Path) -> dict[str, np.ndarray]:
    """Concatenate the bone meshes of every body, in body frames (with the body's geometry offset).

    Returns:
        arrays for ``bones.npz``: vertices (V, 3) float32, faces (F, 3) int32, vertex_body (V,) int16,
        body_names (n_body,).
    """
    verts, faces, owner = [], [], []
    count = 0
    for i, body in enumerate(spec.bodies):
        for mesh in body.geometry:
            path = geometry_dir / f"{mesh}.ply"
            if not path.is_file():
                raise AssetError(f"bone mesh {path} is missing; reinstall nimblephysics")
            v, f = read_vtk_ply(path)
            verts.append(v + np.asarray(body.geometry_offset))
            faces.append(f + count)
            owner.append(np.full(len(v), i))
            count += len(v)
    return {
        "vertices": np.concatenate(verts).astype(np.float32),
        "faces": np.concatenate(faces).astype(np.int32),
        "vertex_body": np.concatenate(owner).astype(np.int16),
        "body_names": np.array(spec.body_names),
    }


@dataclass(frozen=True)
class BoneMesh:
    """Bone vertices in body frames (V, 3), triangles (F, 3), each vertex's body and scale segment (V,)."""

    vertices: np.ndarray
    faces: np.ndarray
    vertex_body: np.ndarray
    vertex_segment: np.ndarray

    @classmethod
    def load(cls, spec: SkeletonSpec, folder: Path | None = None) -> BoneMesh:
        """Load ``bones.npz`` (hash-checked) and check that it belongs to ``spec``."""
        with np.load(verified_asset(BONES_ASSET, folder)) as data:
            if list(data["body_names"]) != spec.body_names:
                raise AssetError(
                    f"{BONES_ASSET} was built for another skeleton; rebuild with `bodyfit build-assets`"
                )
            vertex_body = data["vertex_body"].astype(np.int64)
            vertex_segment = np.asarray(spec.body_segment_index, np.int64)[vertex_body]
            return cls(data["vertices"], data["faces"], vertex_body, vertex_segment)


def pose_bones(
    vertices: torch.Tensor,
    vertex_body: torch.Tensor,
    vertex_segment: torch.Tensor,
    frames: torch.Tensor,
    scales: torch.Tensor | None = None,
) -> torch.Tensor:
    """Pose bone vertices.

    Args:
        vertices: (V, 3) in body frames.
        vertex_body: (V,) body index of each vertex; vertex_segment: (V,) its scale segment index.
        frames: (B, n_body, 4, 4) body frames in the world.
        scales: (B, n_seg, 3) segment scale factors, or None.
    Returns:
        (B, V, 3) world positions.
    """
    if frames.ndim != 4 or frames.shape[-2:] != (4, 4):
        raise ShapeError(f"frames must have shape (B, n_body, 4, 4); got {tuple(frames.shape)}")
    v = vertices.to(frames.dtype).unsqueeze(0)
    if scales is not None:
        v = v * scales[:, vertex_segment]
    T = frames[:, vertex_body]  # (B, V, 4, 4)
    return (T[..., :3, :3] @ v.unsqueeze(-1)).squeeze(-1) + T[..., :3, 3]

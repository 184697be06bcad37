"""Render the body-model gallery: sampled bodies in several poses, skin translucent, skeleton inside.

    python scripts/gallery.py [--out docs/gallery] [--assets DIR]

Writes one PNG per pose (front and side view of every body, side by side) and prints the files written.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from bodyfit.models.body.model import BodyModel

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/ is not installed
from benchmarks.render import RenderMesh, render, save_png, tile

# Poses by name: DOF name -> degrees (both sides unless the name has a side).
POSES: dict[str, dict[str, float]] = {
    "neutral": {"arm_add_r": -10, "arm_add_l": -10},
    "walk": {
        "hip_flexion_r": 30, "knee_angle_r": 15, "ankle_angle_r": 5,
        "hip_flexion_l": -15, "knee_angle_l": 40, "ankle_angle_l": -15,
        "arm_flex_r": -25, "arm_flex_l": 30, "elbow_flex_r": 20, "elbow_flex_l": 40,
        "arm_add_r": -8, "arm_add_l": -8, "thorax_rotation": 6,
    },
    "squat": {
        "hip_flexion_r": 95, "hip_flexion_l": 95, "knee_angle_r": 110, "knee_angle_l": 110,
        "ankle_angle_r": 25, "ankle_angle_l": 25, "lumbar_extension": -20,
        "arm_flex_r": 80, "arm_flex_l": 80, "elbow_flex_r": 90, "elbow_flex_l": 90,
        "pro_sup_r": 0, "pro_sup_l": 90,
    },
    "reach": {
        "arm_add_r": -110, "scapula_upward_rot_r": 30, "elbow_flex_r": 10, "arm_flex_l": 60,
        "elbow_flex_l": 120, "pro_sup_l": 90, "thorax_bending": -10, "lumbar_bending": -10,
        "neck_rotation": 30, "hip_adduction_r": -20, "knee_angle_r": 20,
    },
}  # fmt: skip


def _coordinates(body: BodyModel, degrees: dict[str, float]) -> np.ndarray:
    q = body.skeleton.coordinates({k: np.deg2rad(v) for k, v in degrees.items()})
    lo, hi = body.skeleton.ranges[:, 0], body.skeleton.ranges[:, 1]
    return np.clip(q, lo, hi)


def _shapes(body: BodyModel) -> np.ndarray:
    """The mean body and three held-out bodies of the population (the most different ones)."""
    held = body.data["heldout_shape"].astype(np.float64)
    order = np.argsort(held[:, 0])
    return np.stack([np.zeros(body.n_shape), held[order[0]], held[order[len(order) // 2]], held[order[-1]]])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/gallery"))
    parser.add_argument("--assets", type=Path, default=None)
    parser.add_argument("--size", type=int, default=220, help="image width per view in pixels")
    args = parser.parse_args()
    body = BodyModel.load(args.assets)
    bones_faces = body.skeleton.bone_mesh().faces
    shapes = _shapes(body)
    size = (args.size, int(args.size * 1.5))
    for name, degrees in POSES.items():
        q = np.repeat(_coordinates(body, degrees), len(shapes), axis=0)
        out = body.forward(shapes, q, skeleton_mesh=True, dtype=torch.float64)
        assert out.bones is not None
        images = []
        for view in ("front", "side"):
            lo = out.vertices.numpy().reshape(-1, 3).min(axis=0)
            hi = out.vertices.numpy().reshape(-1, 3).max(axis=0)
            for v, b in zip(out.vertices.numpy(), out.bones.numpy()):
                meshes = [
                    RenderMesh(b, bones_faces, (0.93, 0.90, 0.80)),
                    RenderMesh(v, body.faces, (0.85, 0.55, 0.45), opacity=0.35),
                ]
                images.append(render(meshes, view, size, bounds=(lo, hi)))
        path = args.out / f"{name}.png"
        save_png(tile(images, columns=len(shapes)), path)
        print(path)


if __name__ == "__main__":
    main()

"""Side views of the SMPL upgrade on the test clip: the input SMPL mesh (blue), path (a) with the model file
(orange) and path (b) from the rotations alone (green, placed on path (a)'s position), frames 10 and 40.
The figure is labelled: column titles, each row's frame and path (a)'s mean distance from our skin to the
input mesh on it, and a caption saying what the colours mean. Takes about a minute on 2 cores.

Usage: python benchmarks/upgrade_gallery.py [OUT.png]   (default docs/upgrade_check.png)
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch
from render import RenderMesh, label_grid, render, save_png, tile  # benchmarks/ is on sys.path

from bodyfit.io.smpl import read_smpl_sequence
from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.registered.smpl_topology import SMPL_TO_BODY
from bodyfit.models.fitting.retarget.fitter import wrap_pelvis
from bodyfit.models.upgrade.smpl_model import load_smpl_model
from bodyfit.models.upgrade.upgrade import (
    UpgradeResult,
    upgrade_fitter,
    upgrade_from_rotations,
    upgrade_with_model,
)

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "smpl_format"
FRAMES = (10, 40)
FONT_PX = 18
COLUMNS = [
    "input: the SMPL-format mesh",
    "path (a): with the model file",
    "path (b): from the rotations alone",
]
CAPTION = (
    "Side views of the test clip (CMU subject 131, trial 1). Blue: the input SMPL-format mesh. Orange: our "
    "body by path (a), fitted with the SMPL-format model file. Green: our body by path (b), from the joint "
    "rotations alone, placed at path (a)'s position. Beside each frame: path (a)'s mean distance from our "
    "skin vertices to their points on the input mesh."
)


def skin(model: BodyModel, result: UpgradeResult, t: int) -> np.ndarray:
    q = wrap_pelvis(result.coordinates[t : t + 1], model.skeleton)
    with torch.no_grad():
        out = model.forward(result.shape[None], q, result.root[t : t + 1], offsets=result.offsets)
    return out.vertices.numpy()[0]


def main(out: Path) -> None:
    model = BodyModel.load()
    smpl = load_smpl_model(DATA / "smpl_like_model.npz")
    seq = read_smpl_sequence(DATA / "cmu_131_smpl.npz")
    a = upgrade_with_model(seq, smpl, upgrade_fitter(model))
    b = upgrade_from_rotations(seq, model)
    meshes, _ = smpl.forward(seq.poses, seq.betas, seq.trans)
    images = []
    row_titles = []
    for t in FRAMES:
        row_titles.append(f"frame {t}\n\npath (a), skin\nto input mesh:\n{a.error_mm[t]:.1f} mm")
        body = meshes[t] @ SMPL_TO_BODY.T
        va, vb = skin(model, a, t), skin(model, b, t)
        vb = vb - vb.mean(0) + va.mean(0)
        bounds = (np.minimum(body.min(0), va.min(0)) - 0.05, np.maximum(body.max(0), va.max(0)) + 0.05)
        for verts, faces, color in (
            (body, smpl.faces, (0.6, 0.6, 0.9)),
            (va, model.faces, (0.9, 0.6, 0.5)),
            (vb, model.faces, (0.5, 0.8, 0.5)),
        ):
            images.append(render([RenderMesh(verts, faces, color)], "side", (256, 384), bounds=bounds))
    save_png(label_grid(tile(images, 3), [COLUMNS], row_titles, CAPTION, font_size=FONT_PX), out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "docs" / "upgrade_check.png")

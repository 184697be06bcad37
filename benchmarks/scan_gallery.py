"""Fits of real scans, rendered for docs/: the two CC BY bodies as bare point clouds (their 6,890 vertices,
no faces, turned at random; orientation searched) and the real Kinect scan (tests/data/scans; the person
cropped as the points nearer than 1 m to the camera; camera axes: +Y down, the person seen in profile,
facing the camera's +X).

Writes ``docs/scan_fits.png`` (a row per scan: the input points, the CC BY body's own mesh, our
registration; the Kinect row: the points and the fit as the camera saw them, and the fit from ahead; it is
fitted as a head and shoulders) and prints each fit's report.

Usage::

    python benchmarks/scan_gallery.py [--out docs/scan_fits.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from render import RenderMesh, render, save_png, tile  # benchmarks/ is on sys.path

from bodyfit.io.scans import load_scan
from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.registered.smpl_topology import SMPL_TO_BODY, SOURCE_DIR, SOURCES, read_obj
from bodyfit.models.fitting.scan.fitter import ScanFit, ScanFitter

KINECT = (
    Path(__file__).resolve().parents[1] / "tests" / "data" / "scans" / "pcl_template_alignment_person.pcd"
)
KINECT_TO_BODY = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # +Y down; faces camera +X
KINECT_CROP_M = 1.0
SPLAT_M = 0.004


def splats(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A tiny triangle at every point (N, 3), so the mesh renderer can draw a point cloud."""
    # in the plane x = -z, so both the front (along x) and the side (along z) views see it
    offsets = np.array([[0.0, SPLAT_M, 0.0], [SPLAT_M, -SPLAT_M, -SPLAT_M], [-SPLAT_M, -SPLAT_M, SPLAT_M]])
    verts = (points[:, None, :] + offsets[None]).reshape(-1, 3)
    return verts, np.arange(len(verts)).reshape(-1, 3)


def panel(
    points: np.ndarray,
    fit: ScanFit,
    faces: np.ndarray,
    to_body: np.ndarray,
    truth: RenderMesh | None,
    view: str = "front",
) -> list[np.ndarray]:
    """Views of the points, the truth (when given) and the registration, in the body's axes."""
    lo = (points @ to_body.T).min(0) - 0.05
    hi = (points @ to_body.T).max(0) + 0.05
    v, f = splats(points @ to_body.T)
    images = [render([RenderMesh(v, f, color=(0.3, 0.3, 0.3))], view, (384, 576), bounds=(lo, hi))]
    if truth is not None:
        images.append(render([truth], view, (384, 576), bounds=(lo, hi)))
    reg = RenderMesh(fit.registration @ to_body.T, faces, color=(0.9, 0.6, 0.5))
    images.append(render([reg], view, (384, 576), bounds=(lo, hi)))
    return images


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("docs/scan_fits.png"))
    args = parser.parse_args(argv)
    model = BodyModel.load()
    fitter = ScanFitter(model)
    rng = np.random.default_rng(0)
    images: list[np.ndarray] = []
    for name in SOURCES:
        verts, faces = read_obj(SOURCE_DIR / name)
        R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        R *= np.sign(np.linalg.det(R))
        fit = fitter.fit(verts @ R.T)
        to_body = SMPL_TO_BODY @ R.T
        truth = RenderMesh(verts @ SMPL_TO_BODY.T, faces, color=(0.6, 0.6, 0.9))
        images += panel(verts @ R.T, fit, model.faces, to_body, truth)
        print(f"{name} (bare points, turned): {fit.report.to_dict()}")
    kinect = load_scan(KINECT, drop_nonfinite=True)
    person = kinect.points[kinect.points[:, 2] < KINECT_CROP_M]
    fit = fitter.fit(person, orientation=KINECT_TO_BODY)
    images += panel(person, fit, model.faces, KINECT_TO_BODY, None, view="side")  # the camera's view
    images += panel(person, fit, model.faces, KINECT_TO_BODY, None, view="front")[1:]  # the fit, from ahead
    print(f"kinect (cropped to {len(person)} points): {fit.report.to_dict()}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_png(tile(images, 3), args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

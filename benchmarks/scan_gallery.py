"""Fits of real scans, rendered for docs/: the two CC BY bodies as bare point clouds (their 6,890 vertices,
no faces, turned at random; orientation searched) and the real Kinect scan (tests/data/scans; the person
cropped as the points nearer than 1 m to the camera; camera axes: +Y down, the person seen in profile,
facing the camera's +X).

Writes ``docs/scan_fits.png`` (a row per scan: the input points, the CC BY body's own mesh, our
registration; the Kinect row: the points and the fit as the camera saw them, and the fit from ahead; it is
fitted as a head and shoulders), labelled: each row's title band says what its columns show, the row's
label names the scan and its mean scan-to-model distance, and a caption says what the colours and the
distance mean. Prints each fit's report. Takes about a minute on 2 cores (three fits, nine renders).

Usage::

    python benchmarks/scan_gallery.py [--out docs/scan_fits.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from render import RenderMesh, label_grid, render, save_png, tile  # benchmarks/ is on sys.path

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
FONT_PX = 24
CCBY_COLUMNS = ["input points", "the body's own mesh\n(ground truth)", "our registration"]
KINECT_COLUMNS = [
    "input points,\nas the camera saw them",
    "our registration,\nfrom the camera",
    "our registration,\nfrom ahead",
]
CAPTION = (
    "Dark grey: the input points. Blue: the CC BY body's own mesh, the ground truth. Orange: our "
    "registration. Scan to model: the mean distance from every scan point to the registration's surface."
)


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


def scan_to_model(fit: ScanFit) -> str:
    """A row label's distance: the mean of the report's scan to model (every scan point, outliers too)."""
    if fit.report.scan_to_model is None:
        raise RuntimeError("a raw-scan fit's report should measure every point's distance to the model")
    return f"scan to model\n{fit.report.scan_to_model.mean:.2f} mm"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("docs/scan_fits.png"))
    args = parser.parse_args(argv)
    model = BodyModel.load()
    fitter = ScanFitter(model)
    rng = np.random.default_rng(0)
    images: list[np.ndarray] = []
    row_titles: list[str] = []
    for name in SOURCES:
        verts, faces = read_obj(SOURCE_DIR / name)
        R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        R *= np.sign(np.linalg.det(R))
        fit = fitter.fit(verts @ R.T)
        to_body = SMPL_TO_BODY @ R.T
        truth = RenderMesh(verts @ SMPL_TO_BODY.T, faces, color=(0.6, 0.6, 0.9))
        images += panel(verts @ R.T, fit, model.faces, to_body, truth)
        body = Path(name).stem.removeprefix("human_")
        row_titles.append(
            f"{body} (CC BY)\n{len(verts):,} bare points,\nturned at random\n\n{scan_to_model(fit)}"
        )
        print(f"{name} (bare points, turned): {fit.report.to_dict()}")
    kinect = load_scan(KINECT, drop_nonfinite=True)
    person = kinect.points[kinect.points[:, 2] < KINECT_CROP_M]
    fit = fitter.fit(person, orientation=KINECT_TO_BODY)
    images += panel(person, fit, model.faces, KINECT_TO_BODY, None, view="side")  # the camera's view
    images += panel(person, fit, model.faces, KINECT_TO_BODY, None, view="front")[1:]  # the fit, from ahead
    row_titles.append(
        f"Kinect capture\n{len(person):,} points\nnearer than {KINECT_CROP_M:.0f} m,\nfitted as a head\n"
        f"and shoulders\n\n{scan_to_model(fit)}"
    )
    print(f"kinect (cropped to {len(person)} points): {fit.report.to_dict()}")
    titles = [CCBY_COLUMNS] * len(SOURCES) + [KINECT_COLUMNS]
    figure = label_grid(tile(images, 3), titles, row_titles, CAPTION, font_size=FONT_PX)
    save_png(figure, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

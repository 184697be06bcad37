"""Head-and-shoulders scans of held-out bodies: the scan fit's partial mode, in one run.

What is measured
----------------
* Bodies: the held-out anny bodies and poses of ``fit_scans.py`` (the same seed and spread).
* Scans: each body's top 45 cm (head, neck, shoulders, upper chest; the arms where the pose puts them
  there), in turn ``clean`` (100,000 points on the whole surface, then cropped) and ``depth`` (one virtual
  depth camera 1 m in front of the head, 240 x 320 pixels, then cropped); then turned about a random axis by
  a random angle and moved by up to 1 m.
* Fit: :class:`ScanFitter` with its defaults (orientation searched, no landmarks), one process, torch on
  one thread per op.
* ``head_mm``: mean distance of the registration's head vertices to the truth's (correspondence error);
  ``upper_mm``: the same over the "upper" vertex set the partial mode fits (:data:`UPPER_BODY_M`);
  ``scan_mm``: the fit's own report; ``partial``: the scan was fitted as a head and shoulders (a bust
  whose arms reach out of it measures more than ``ScanFitConfig.partial_extent`` and is fitted as a whole
  body); ``bust_partial_head_within_10mm``: of those fitted as a head and shoulders.

Usage::

    python benchmarks/fit_busts.py [--quick] [--json]
"""

from __future__ import annotations

import time
from typing import Any

import corrupt  # benchmarks/ is on sys.path
import numpy as np
from fit_scans import HELD_OUT_SEED, POINTS, SPREAD, vertex_parts  # benchmarks/ is on sys.path

from bodyfit.io.scans import sample_surface
from bodyfit.models.body.anny_posed import posed_anny_bodies
from bodyfit.models.body.anny_source import AnnySource
from bodyfit.models.body.model import BodyModel
from bodyfit.models.build_assets import default_cache_dir
from bodyfit.models.fitting.scan.fitter import ScanFitter
from bodyfit.models.threads import torch_threads

BUST_M = 0.45
CONDITIONS = ("clean", "depth")
HEAD_WITHIN_MM = 10.0


def make_bust(vertices: np.ndarray, faces: np.ndarray, condition: str, seed: int) -> np.ndarray:
    """(N, 3) points of the top :data:`BUST_M` of one body (V, 3) under ``condition``."""
    if condition == "depth":
        head = vertices[vertices[:, 1] > vertices[:, 1].max() - 0.25].mean(0)
        rng = np.random.default_rng(seed)
        points, _ = corrupt.depth_camera_view(
            vertices, faces, head + np.array([1.0, 0.0, 0.0]), head, (240, 320), rng=rng
        )
    else:
        points, _ = sample_surface(vertices, faces, POINTS, seed)
    return points[points[:, 1] > vertices[:, 1].max() - BUST_M]


def run(quick: bool) -> dict[str, Any]:
    model = BodyModel.load()
    n = 6 if quick else 24
    with torch_threads(2):
        bodies = posed_anny_bodies(AnnySource(default_cache_dir()), model.skeleton, n, HELD_OUT_SEED, SPREAD)
    fitter = ScanFitter(model)
    parts = vertex_parts(model)
    upper = fitter.fitter.index["upper"]
    rows = []
    for k in range(n):
        truth = bodies.vertices[k]
        condition = CONDITIONS[k % len(CONDITIONS)]
        points = make_bust(truth, model.faces, condition, k)
        moved, T = corrupt.random_rigid(points, np.random.default_rng(20_000 + k))
        with torch_threads(1):  # as fit_scans.py: a fit is chaotic in its rounding, which threads change
            start = time.perf_counter()
            fit = fitter.fit(moved)
            seconds = time.perf_counter() - start
        error = np.linalg.norm(fit.registration - (truth @ T[:3, :3].T + T[:3, 3]), axis=1) * 1000
        rows.append({
            "condition": condition,
            "partial": fit.report.extra["fitted_part"] == "head and shoulders",
            "head_mm": float(error[parts == "head"].mean()),
            "upper_mm": float(error[upper].mean()),
            "scan_mm": fit.report.distances.mean,
            "confident": fit.report.confident,
            "seconds": seconds,
        })  # fmt: skip
    fitter.close()
    head = np.array([r["head_mm"] for r in rows])
    partial = np.array([r["partial"] for r in rows])
    return {
        "bust_scans": n,
        "bust_partial_fraction": round(float(partial.mean()), 3),
        "bust_head_mm_median": round(float(np.median(head)), 2),
        "bust_head_within_10mm": round(float(np.mean(head <= HEAD_WITHIN_MM)), 3),
        "bust_partial_head_within_10mm": round(float(np.mean(head[partial] <= HEAD_WITHIN_MM)), 3),
        "bust_upper_mm_median": round(float(np.median([r["upper_mm"] for r in rows])), 2),
        "bust_scan_mm": round(float(np.mean([r["scan_mm"] for r in rows])), 3),
        "bust_confident": int(sum(r["confident"] for r in rows)),
        "bust_s": round(float(np.mean([r["seconds"] for r in rows])), 2),
        "bust_by_condition_head_mm_median": {
            c: round(float(np.median([r["head_mm"] for r in rows if r["condition"] == c])), 2)
            for c in CONDITIONS
        },
    }


def main(argv: list[str] | None = None) -> None:
    from bench_cli import bench_main

    bench_main(run, __doc__.split("\n")[0], "6 scans instead of 24", argv)


if __name__ == "__main__":
    main()

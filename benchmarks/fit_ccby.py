"""Real bodies outside our population: the CC BY bodies in SMPL and SMPL-X topology, fitted by every route.

What is measured
----------------
* Bodies: ``data/smpl_ccby/human_man.obj`` and ``human_woman.obj`` (SMPL topology, 6,890 vertices; Max
  Planck Society via SMPL, CC BY 4.0, see data/smpl_ccby/README.md) and, when ``../shared/data`` holds it,
  ``meshes_smpl_ccby/human_neutral.obj`` (SMPL-X topology, 10,475 vertices; via SMPL-X, CC BY 4.0). All in
  T-pose, metres, +Y up.
* Routes: ``raw`` (100,000 points sampled uniformly on the surface, turned about a random axis by a random
  angle and moved by up to 0.5 m, fitted by :class:`ScanFitter` with its defaults, orientation searched, as
  the service runs it) and ``smpl`` (the SMPL-topology route, :func:`fit_smpl_mesh`: the mesh placed through
  the topology map and refined on its surface; the SMPL-topology bodies only).
* ``fit_to_scan``: each registration vertex's distance to the input mesh's surface (exact point-to-triangle
  distance), over the vertices a scan can show: those visible from outside in our template (the mean body
  in a T-pose, rendered from 40 directions around it). The template's mouth and eye cavities (about 900
  vertices, all in the head) are never visible, and no scan of a real person has them. ``_all`` variants
  take every vertex.
* ``scan_to_fit``: each surface sample's distance to the registration's surface (the other direction).
* ``param_fit_to_scan``: the same as ``fit_to_scan`` for the parametric fit (before the non-rigid
  registration): what the shape space explains.
* Keys: ``ccby_fit_to_scan_mm`` the worst route/body mean fit-to-scan, ``ccby_fit_to_scan_max_mm`` the
  worst maximum; per body and route the rows in ``ccby_rows``. Targets (issue): mean <= 3 mm, max <= 15 mm.

Usage::

    python benchmarks/fit_ccby.py [--quick] [--json]
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import corrupt  # benchmarks/ is on sys.path
import numpy as np
import torch

from bodyfit.io.scans import sample_surface
from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common.surface import point_to_surface
from bodyfit.models.fitting.registered.fitter import RegisteredFitter
from bodyfit.models.fitting.registered.smpl_topology import SOURCE_DIR, fit_smpl_mesh, read_obj, t_pose
from bodyfit.models.fitting.scan.fitter import ScanFit, ScanFitter
from bodyfit.models.threads import torch_threads

ROOT = Path(__file__).resolve().parents[1]
NEUTRAL = ROOT.parent / "shared" / "data" / "meshes_smpl_ccby" / "human_neutral.obj"
POINTS = 100_000
VIEWS = 40  # directions the template is rendered from to find the vertices a scan can show
SEED = 30_000


def bodies() -> dict[str, Path]:
    """The CC BY bodies on this machine, by name."""
    found = {"man": SOURCE_DIR / "human_man.obj", "woman": SOURCE_DIR / "human_woman.obj"}
    if NEUTRAL.exists():
        found["neutral"] = NEUTRAL
    return found


def visible_vertices(model: BodyModel, views: int = VIEWS) -> np.ndarray:
    """(V,) bool, our template's vertices visible from outside: the mean body in a T-pose rendered (a depth
    camera 4 m away, 600 x 600 pixels, about 4 mm each) from ``views`` directions spread evenly over the
    sphere (a Fibonacci lattice)."""
    ranges = model.skeleton.ranges
    q = np.clip(t_pose(model), ranges[:, 0], ranges[:, 1])
    v = model.forward(None, torch.as_tensor(q)[None], None).vertices[0].detach().numpy().astype(np.float64)
    centre = v.mean(0)
    k = np.arange(views) + 0.5
    polar, azimuth = np.arccos(1 - 2 * k / views), np.pi * (1 + 5**0.5) * k
    directions = np.stack(
        [np.cos(azimuth) * np.sin(polar), np.cos(polar), np.sin(azimuth) * np.sin(polar)], 1
    )
    hit = np.zeros(len(model.faces), bool)
    for d in directions:
        up = (0.0, 1.0, 0.0) if abs(d[1]) < 0.9 else (1.0, 0.0, 0.0)
        _, faces = corrupt.depth_camera_view(v, model.faces, centre + 4 * d, centre, (600, 600), 32.0, up=up)
        hit[faces] = True
    seen = np.zeros(len(v), bool)
    seen[model.faces[hit].ravel()] = True
    return seen


def measure(
    fit: ScanFit,
    mesh: np.ndarray,
    faces: np.ndarray,
    samples: np.ndarray,
    body_faces: np.ndarray,
    seen: np.ndarray,
) -> dict[str, float]:
    """Distances (mm) of a fit (registration and parametric vertices (V, 3), in the mesh's frame) to the
    input mesh (N, 3), (F, 3) both ways; ``samples`` (S, 3) on the mesh's surface; ``seen`` (V,) the
    vertices a scan can show."""
    fit_to_scan = point_to_surface(fit.registration, mesh, faces) * 1000
    param = point_to_surface(fit.vertices, mesh, faces) * 1000
    scan_to_fit = point_to_surface(samples, fit.registration, body_faces) * 1000
    return {
        "fit_to_scan_mm": round(float(fit_to_scan[seen].mean()), 3),
        "fit_to_scan_p99_mm": round(float(np.percentile(fit_to_scan[seen], 99)), 2),
        "fit_to_scan_max_mm": round(float(fit_to_scan[seen].max()), 2),
        "fit_to_scan_all_mm": round(float(fit_to_scan.mean()), 3),
        "fit_to_scan_all_max_mm": round(float(fit_to_scan.max()), 2),
        "scan_to_fit_mm": round(float(scan_to_fit.mean()), 3),
        "scan_to_fit_max_mm": round(float(scan_to_fit.max()), 2),
        "param_fit_to_scan_mm": round(float(param[seen].mean()), 3),
        "param_fit_to_scan_max_mm": round(float(param[seen].max()), 2),
    }


def fit_routes(
    name: str, path: Path, k: int, scanner: ScanFitter, registered: RegisteredFitter, seen: np.ndarray
) -> list[dict[str, Any]]:
    """Body ``name`` (an OBJ at ``path``; its index ``k`` seeds the samples and the motion) by every route
    that takes it."""
    verts, faces = read_obj(path)
    body_faces = scanner.model.faces
    samples, _ = sample_surface(verts, faces, POINTS, seed=k)
    moved, T = corrupt.random_rigid(samples, np.random.default_rng(SEED + k), translation=0.5)
    mesh = verts @ T[:3, :3].T + T[:3, 3]
    rows = []
    start = time.perf_counter()
    fit = scanner.fit(moved)
    rows.append({"body": name, "route": "raw", "seconds": round(time.perf_counter() - start, 2),
                 **measure(fit, mesh, faces, moved, body_faces, seen)})  # fmt: skip
    if len(verts) == 6890:
        start = time.perf_counter()
        fit = fit_smpl_mesh(registered, scanner, verts, faces)
        rows.append({"body": name, "route": "smpl", "seconds": round(time.perf_counter() - start, 2),
                     **measure(fit, verts, faces, samples, body_faces, seen)})  # fmt: skip
    return rows


def run(quick: bool) -> dict[str, Any]:
    """Every body by every route (``quick`` changes nothing: three bodies, five fits, about 20 s)."""
    del quick
    model = BodyModel.load()
    seen = visible_vertices(model)
    scanner, registered = ScanFitter(model), RegisteredFitter(model)
    rows: list[dict[str, Any]] = []
    try:
        with torch_threads(1):
            for k, (name, path) in enumerate(bodies().items()):
                rows.extend(fit_routes(name, path, k, scanner, registered, seen))
    finally:
        scanner.close()
    return {
        "ccby_fit_to_scan_mm": max(r["fit_to_scan_mm"] for r in rows),
        "ccby_fit_to_scan_max_mm": max(r["fit_to_scan_max_mm"] for r in rows),
        "ccby_scan_to_fit_mm": max(r["scan_to_fit_mm"] for r in rows),
        "ccby_param_fit_to_scan_mm": max(r["param_fit_to_scan_mm"] for r in rows),
        "ccby_visible_vertices": int(seen.sum()),
        "ccby_rows": rows,
    }


def main(argv: list[str] | None = None) -> None:
    from bench_cli import bench_main

    bench_main(run, __doc__.split("\n")[0], "the same run (it is short)", argv)


if __name__ == "__main__":
    main()

"""Registered-mesh fitting: ours against anny's AnnyInverter on the same held-out posed bodies, one run.

What is measured
----------------
* Bodies: adults sampled from anny's shape distribution with a seed the asset build never used
  (``HELD_OUT_SEED``), the skeleton placed inside each from its landmarks, posed to random coordinates
  (uniform within half of every range about its middle), skinned by anny's own rig and weights
  (:mod:`bodyfit.models.body.anny_posed`). Each body is then turned about the vertical by a random angle and
  moved by up to 1 m (a rigid motion both fitters must undo).
* Ours: :class:`RegisteredFitter` with default stages, float32, all bodies in one batch, on our template's
  13,348 vertices; time includes the start (per-body Kabsch + inverse kinematics).
* anny: ``AnnyInverter(anny.Anny())`` (float32) on anny's whole mesh in anny's own frame (its own topology),
  all six phenotypes and the pose optimised, ``post_gd=True`` (100 Adam steps): the accurate setting of
  ../shared/facts/anny.md section 7 (about 1.3-2.4 mm there). Same bodies, batches of ``ANNY_BATCH``.
* Error: mean per-vertex distance (mm) over our template's vertices (anny's vertices minus eyes and tongue),
  for both, against the same targets. Time: wall time per mesh (ms), on this machine's CPU threads.
* Targets (issue): ours <= 2 mm mean at <= 50 ms per mesh.

Usage::

    python benchmarks/fit_registered.py [--quick] [--json]
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from bodyfit.models.body.anny_posed import PosedBodies, posed_anny_bodies
from bodyfit.models.body.anny_source import ANNY_TO_OURS, AnnySource
from bodyfit.models.body.model import BodyModel
from bodyfit.models.build_assets import default_cache_dir
from bodyfit.models.fitting.registered.fitter import RegisteredFitter

HELD_OUT_SEED = 4242  # the build uses 20261122 (+1, +2)
ANNY_BATCH = 8
TARGET_MM = 2.0
TARGET_MS = 50.0


def moved(bodies: PosedBodies, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Random turns about the vertical and shifts, applied to both meshes of every body.

    Returns:
        ours (N, V, 3) in our frame; anny's (N, V_anny, 3) in anny's frame.
    """
    n = len(bodies.vertices)
    R = Rotation.from_euler("y", rng.uniform(-np.pi, np.pi, (n, 1))).as_matrix()  # (N, 3, 3), ours
    t = rng.uniform(-1.0, 1.0, (n, 3)) * np.array([1.0, 0.1, 1.0])
    ours = np.einsum("nij,nvj->nvi", R, bodies.vertices) + t[:, None]
    C = ANNY_TO_OURS
    R_anny = C.T @ R @ C
    anny = np.einsum("nij,nvj->nvi", R_anny, bodies.anny_vertices) + (t @ C)[:, None]
    return ours, anny


def run_ours(model: BodyModel, targets: np.ndarray) -> tuple[np.ndarray, float]:
    """Per-body mean vertex error (mm) and ms per mesh."""
    fitter = RegisteredFitter(model)
    start = time.perf_counter()
    fit = fitter.fit(targets)
    ms = (time.perf_counter() - start) * 1000 / len(targets)
    assert all(r.limit_violations == 0 for r in fit.reports)
    return np.array([r.distances.mean for r in fit.reports]), ms


def run_anny(src: AnnySource, targets: np.ndarray) -> tuple[np.ndarray, float]:
    """AnnyInverter on anny's own topology; errors over our template's vertices (mm), ms per mesh."""
    import anny
    from anny.anny_inverter import AnnyInverter

    model = anny.Anny().to(torch.float32)
    inverter = AnnyInverter(model)
    errors, seconds = [], 0.0
    for start in range(0, len(targets), ANNY_BATCH):
        x = torch.as_tensor(targets[start : start + ANNY_BATCH], dtype=torch.float32)
        t0 = time.perf_counter()
        _, _, v_hat = inverter(x, post_gd=True)
        seconds += time.perf_counter() - t0
        d = (v_hat.detach().double() - x.double()).norm(dim=-1)[:, torch.as_tensor(src.keep)]
        errors.append(d.mean(dim=1).numpy() * 1000)
    return np.concatenate(errors), seconds * 1000 / len(targets)


def run(quick: bool) -> dict[str, Any]:
    """Both fitters on the same bodies; returns the figures (JSON-ready)."""
    torch.manual_seed(0)
    n_ours, n_anny = (24, 8) if quick else (200, 200)
    model = BodyModel.load()
    src = AnnySource(default_cache_dir())
    bodies = posed_anny_bodies(src, model.skeleton, n_ours, HELD_OUT_SEED)
    ours_x, anny_x = moved(bodies, np.random.default_rng(HELD_OUT_SEED))
    ours_err, ours_ms = run_ours(model, ours_x)
    anny_err, anny_ms = run_anny(src, anny_x[:n_anny])
    return {
        "registered_bodies": n_ours,
        "registered_mm": round(float(ours_err.mean()), 3),
        "registered_mm_max": round(float(ours_err.max()), 3),
        "registered_ms": round(ours_ms, 1),
        "anny_bodies": n_anny,
        "anny_mm": round(float(anny_err.mean()), 3),
        "anny_mm_max": round(float(anny_err.max()), 3),
        "anny_ms": round(anny_ms, 1),
        "registered_speed_ratio": round(anny_ms / ours_ms, 1),
        "registered_targets_met": bool(ours_err.mean() <= TARGET_MM and ours_ms <= TARGET_MS),
    }


def show(r: dict[str, Any]) -> None:
    print(f"ours : {r['registered_mm']:.2f} mm mean ({r['registered_mm_max']:.2f} worst body), "
          f"{r['registered_ms']:.1f} ms/mesh over {r['registered_bodies']} bodies")  # fmt: skip
    print(f"anny : {r['anny_mm']:.2f} mm mean ({r['anny_mm_max']:.2f} worst body), "
          f"{r['anny_ms']:.1f} ms/mesh over {r['anny_bodies']} bodies")  # fmt: skip
    print(f"speed: ours {r['registered_speed_ratio']}x faster; targets met: {r['registered_targets_met']}")


def main(argv: list[str] | None = None) -> None:
    from bench_cli import bench_main  # benchmarks/ is on sys.path when this runs as a script

    bench_main(run, __doc__.split("\n")[0], "24 bodies for us, 8 for anny", argv, show)


if __name__ == "__main__":
    main()

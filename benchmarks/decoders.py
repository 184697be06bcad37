"""Learned identity decoders against the identity PCA at equal size, and their ONNX speed, in one run.

What is measured
----------------
* Bodies: the asset build's population (anny, its seed and size), regenerated and unposed to the bind pose
  as the build does (:mod:`bodyfit.models.decoders.population`; cached under build/decoders, keyed by the
  body model's hash); each body's identity offsets are its bind-pose mesh minus the shipped model's
  bone-corrected template for its bone coefficients. The decoders train on the 90 % the build trains on;
  ``heldout`` is the build's held-out tenth; ``children`` (ages 5 to 18) and ``extreme`` (adults with every
  phenotype slider at 0.02 or 0.98) lie outside the training population.
* ``spiral_mm_d<d>``: mean per-vertex distance (mm) between a held-out body's identity offsets and the
  spiral decoder's, its code fitted by Levenberg-Marquardt from the body's PCA projection (8 iterations).
  ``pca_mm_d<d>``: the same for the projection on a d-component identity PCA fitted on the same training
  bodies in this run (the best the linear space holds). ``spiral_ratio_d<d>`` = spiral / PCA; the same
  with ``_children`` and ``_extreme`` for the bodies outside the population; ``*_max_mm``: worst vertex.
* d = 8: the shipped decoder (``assets/spiral_d8.npz``). Full run: also d = 4, 16, 32, from the
  checkpoints in build/decoders (``bodyfit decoders train --d D --no-save``), trained when missing.
  Quick: 50 held-out bodies and 30 of each outside set; full: all of them (200, 100, 100).
* ``spiral_onnx_ms_b1``: the body decoder with the spiral identity term exported to ONNX
  (:func:`export_spiral_onnx`), one body, median of interleaved calls; ``linear_onnx_ms_b1``: the shipped
  ``body.onnx`` in the same loop. ONNX Runtime on the CPU, all cores, all graph optimisations.
  ``spiral_onnx_parity_m``: largest vertex or joint difference between ONNX and torch over 16 random bodies
  and poses (codes within 2 standard deviations).
* ``markers_body_mm``: bodies of the NHANES population (quick: one per sex; full: three) walking 40 frames
  at 60 Hz, the markers of the gait2392 and the Rajagopal sets each moving with the skin vertex nearest its
  virtual place, 9.5 mm out along the normal, 5 mm Gaussian noise, 10 % dropouts; fitted through
  ``fit_markers`` (motion calibration) and the skin step (:mod:`bodyfit.models.fitting.mocap.skin`): mean
  per-vertex distance (mm) to the true skin in the same frames. ``markers_body_mean_identity_mm``: the
  mean-identity body on the same fitted skeleton and poses (no skin estimate). ``*_true_pose_*``: the same
  two with the skin step given the true skeleton and poses (the skin step alone).
* Targets (issue 41): ``spiral_ratio_d8`` <= 0.7, ``markers_body_mm`` <= 12, ``spiral_onnx_ms_b1`` <= 2.0,
  parity <= 1e-5 m.

Usage::

    python benchmarks/decoders.py [--quick] [--json]
    python benchmarks/decoders.py images    # docs/decoders_*.png: held-out error maps, spiral against PCA
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
QUICK_LIMIT, OUTSIDE_LIMIT = 50, 30
SWEEP = (4, 16, 32)
TRAIN_MINUTES = 14.0


def _comparisons(trained: Any, sets: dict[str, Any], d: int, quick: bool) -> dict[str, float]:
    from bodyfit.models.decoders.pipeline import evaluate

    result = evaluate(trained, sets, d, QUICK_LIMIT if quick else None, OUTSIDE_LIMIT if quick else None)
    heldout = result["heldout"]
    out = {
        f"spiral_mm_d{d}": round(heldout["spiral_mm"], 3),
        f"pca_mm_d{d}": round(heldout["pca_mm"], 3),
        f"spiral_ratio_d{d}": round(heldout["ratio"], 3),
        f"spiral_max_mm_d{d}": round(heldout["spiral_max_mm"], 2),
        f"pca_max_mm_d{d}": round(heldout["pca_max_mm"], 2),
    }
    for name in ("children", "extreme"):
        r = result[name]
        out[f"spiral_mm_d{d}_{name}"] = round(r["spiral_mm"], 3)
        out[f"pca_mm_d{d}_{name}"] = round(r["pca_mm"], 3)
        out[f"spiral_ratio_d{d}_{name}"] = round(r["ratio"], 3)
    return out


def _sweep_model(d: int, work: Path) -> Any:
    from bodyfit.models.decoders.pipeline import train_decoder
    from bodyfit.models.decoders.train import load_checkpoint

    path = work / f"spiral_d{d}.pt"
    if not path.is_file():
        train_decoder(d, TRAIN_MINUTES, work, log=lambda m: print(m, file=sys.stderr))
    return load_checkpoint(path)[0]


def _session(data: bytes | str) -> Any:
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.log_severity_level = 3
    options.intra_op_num_threads = os.cpu_count() or 1
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return ort.InferenceSession(data, options, providers=["CPUExecutionProvider"])


def _inputs(n_shape: int, n_dof: int, batch: int, rng: np.random.Generator) -> dict[str, Any]:
    shape = rng.normal(size=(batch, n_shape)).clip(-2, 2).astype(np.float32)
    return {
        "shape": shape,
        "coordinates": (0.2 * rng.normal(size=(batch, n_dof))).astype(np.float32),
        "root": np.zeros((batch, 3), np.float32),
    }


def _onnx(quick: bool) -> dict[str, float]:
    """ONNX timings (B = 1) of the spiral and the linear body decoders, and the spiral one's parity."""
    from bodyfit.models.assets import verified_asset
    from bodyfit.models.body.onnx_export import BODY_ONNX
    from bodyfit.models.decoders.asset import SpiralBodyModel
    from bodyfit.models.decoders.export import export_spiral_onnx

    model = SpiralBodyModel.load(8)
    rng = np.random.default_rng(0)
    clipped = model.body.skeleton.ranges
    spiral = _session(export_spiral_onnx(model.module))
    linear = _session(str(verified_asset(BODY_ONNX)))
    n_dof = model.body.skeleton.n_dof
    feeds = {
        "spiral": _inputs(model.n_shape, n_dof, 1, rng),
        "linear": _inputs(model.body.n_shape, n_dof, 1, rng),
    }
    times: dict[str, list[float]] = {"spiral": [], "linear": []}
    for _ in range(50 if quick else 300):
        for name, sess in (("spiral", spiral), ("linear", linear)):
            t0 = time.perf_counter()
            sess.run(None, feeds[name])
            times[name].append(time.perf_counter() - t0)
    parity = 0.0
    for _ in range(16):
        f = _inputs(model.n_shape, n_dof, 1, rng)
        f["coordinates"] = np.clip(f["coordinates"], clipped[:, 0], clipped[:, 1]).astype(np.float32)
        v, j = spiral.run(None, f)
        ref = model.forward(f["shape"], f["coordinates"], f["root"])
        parity = max(parity, float(np.abs(v - ref.vertices.numpy()).max()),
                     float(np.abs(j - ref.joints.numpy()).max()))  # fmt: skip
    return {
        "spiral_onnx_ms_b1": round(1e3 * float(np.median(times["spiral"][5:])), 3),
        "linear_onnx_ms_b1": round(1e3 * float(np.median(times["linear"][5:])), 3),
        "spiral_onnx_parity_m": float(f"{parity:.3g}"),
    }


def run(quick: bool) -> dict[str, Any]:
    from bodyfit.models.body.model import BodyModel
    from bodyfit.models.decoders.asset import load_asset
    from bodyfit.models.decoders.pipeline import default_work_dir, identity_sets
    from bodyfit.models.decoders.train import Trained

    torch.set_num_threads(1)
    work = default_work_dir()
    sets = identity_sets(BodyModel.load(), work)
    asset = load_asset(8)
    shipped = Trained(asset.decoder, asset.latent_mean, asset.latent_std)
    out: dict[str, Any] = {"quick": quick, "pca": "identity PCA fitted on the same training bodies"}
    out.update(_comparisons(shipped, sets, 8, quick))
    if not quick:
        for d in SWEEP:
            out.update(_comparisons(_sweep_model(d, work), sets, d, quick))
    out.update(_onnx(quick))
    out.update(_markers_body(quick))
    return out


# Synthetic marker trials for ``markers_body_mm``: frames, rate, noise, dropout fraction.
MARKER_FRAMES, MARKER_RATE, MARKER_NOISE, MARKER_DROPOUT = 40, 60.0, 0.005, 0.10


def _gait(model: Any, n: int) -> tuple[np.ndarray, np.ndarray]:
    """A walking-like cycle: coordinates (n, n_dof) within range and roots (n, 3), 1.2 m/s forward."""
    phase = np.linspace(0.0, 2.0 * np.pi, n)
    amp = {"hip_flexion": (0.15, 0.45), "knee_angle": (0.55, 0.55), "ankle_angle": (0.0, 0.25),
           "arm_flex": (0.0, 0.35), "elbow_flex": (0.5, 0.3), "lumbar_rotation": (0.0, 0.1)}  # fmt: skip
    q = np.zeros((n, model.skeleton.n_dof))
    for i, name in enumerate(model.dof_names):
        for key, (mid, a) in amp.items():
            if name.startswith(key):
                side = np.pi if name.endswith("_l") else 0.0
                q[:, i] = mid + a * np.sin(phase + side + (np.pi if key == "arm_flex" else 0.0))
    q = np.clip(q, model.skeleton.ranges[:, 0], model.skeleton.ranges[:, 1])
    root = np.zeros((n, 3))
    root[:, 0] = 1.2 * np.arange(n) / MARKER_RATE
    root[:, 1] = 0.95
    return q, root


def _skin_markers(model: Any, set_name: str, out: Any, rng: np.random.Generator) -> Any:
    """A marker trial of the set ``set_name`` on posed bodies ``out`` (BodyOutput, T frames): each virtual
    marker moves with the skin vertex nearest its place on the first frame, :data:`MARKER_OFFSET` out along
    the normal; Gaussian noise and random dropouts."""
    from bodyfit.io.mocap import MarkerTrial
    from bodyfit.models.body.model import body_points
    from bodyfit.models.fitting.common.surface import vertex_normals
    from bodyfit.models.fitting.mocap.calibration import virtual_markers
    from bodyfit.models.fitting.mocap.marker_sets import MARKER_SETS
    from bodyfit.models.fitting.mocap.skin import MARKER_OFFSET

    vm = virtual_markers(MARKER_SETS[set_name], model)
    skel = model.skeleton
    bodies = vm.body_indices(skel)
    segments = torch.as_tensor([skel.spec.body_segment_index[b] for b in bodies])
    everywhere = body_points(out.frames.double(), out.scales.double(), torch.as_tensor(bodies), segments,
                             torch.as_tensor(vm.local)).numpy()  # fmt: skip
    verts = out.vertices.double().numpy()
    nearest = np.linalg.norm(verts[0][None] - everywhere[0][:, None], axis=-1).argmin(1)
    normals = vertex_normals(verts, model.faces)[:, nearest]
    pos = verts[:, nearest] + MARKER_OFFSET * normals
    # joint-centre "markers" (RHJC, R_KJC, ...) are computed by the lab inside the body: they stay there
    centres = np.array(["JC" in name for name in vm.names])
    pos[:, centres] = everywhere[:, centres]
    pos += rng.normal(0.0, MARKER_NOISE, pos.shape)
    pos[rng.random(pos.shape[:2]) < MARKER_DROPOUT] = np.nan
    times = np.arange(len(pos)) / MARKER_RATE
    return MarkerTrial(tuple(vm.names), pos, MARKER_RATE, times, f"synthetic {set_name}")


def _markers_body(quick: bool) -> dict[str, Any]:
    """``markers_body_mm``: NHANES bodies (both sexes) walking with the markers of both sets on their skin,
    fitted through fit_markers and the skin step: mean per-vertex distance (mm) to the true skin in the same
    frames; ``markers_body_mean_identity_mm``: the mean-identity body on the same fitted skeleton and poses.
    ``*_true_pose_mm``: the skin step alone, on the true skeleton and poses."""
    from bodyfit.models.body.model import BodyModel

    model = BodyModel.load()
    per_sex = 1 if quick else 3
    shapes = np.concatenate([model.sample(per_sex, sex, "nhanes", seed=41) for sex in ("male", "female")])
    q, root = _gait(model, MARKER_FRAMES)
    rng = np.random.default_rng(41)
    rows = []
    for i, shape in enumerate(shapes):
        truth = model.forward(np.repeat(shape[None], len(q), 0), q, root)
        for set_name in ("gait2392", "rajagopal"):
            trial = _skin_markers(model, set_name, truth, rng)
            rows.append({"body": i, "set": set_name, **_marker_body_errors(model, trial, truth, q, root)})
    mean = {key: float(np.mean([r[key] for r in rows])) for key in rows[0] if key.endswith("_mm")}
    return {
        "markers_body_mm": mean["fit_mm"],
        "markers_body_mean_identity_mm": mean["mean_identity_mm"],
        "markers_body_true_pose_mm": mean["true_pose_fit_mm"],
        "markers_body_true_pose_mean_identity_mm": mean["true_pose_mean_identity_mm"],
        "markers_body_max_mm": float(np.max([r["fit_mm"] for r in rows])),
        "markers_body_trials": rows,
    }


def _marker_body_errors(
    model: Any, trial: Any, truth: Any, q: np.ndarray, root: np.ndarray
) -> dict[str, float]:
    """Per-vertex distances (mm) to ``truth`` of the skin fitted from ``trial`` and of the mean-identity body,
    on the fitted skeleton and poses and on the true ones."""
    from bodyfit.models.fitting.mocap.fitter import fit_markers, observed_positions
    from bodyfit.models.fitting.mocap.skin import fit_skin

    fit = fit_markers(trial, model=model)
    observed = observed_positions(trial, list(fit.markers.names))
    true_v = truth.vertices.numpy()
    out = {}
    cases = {"": (fit.scales, fit.coordinates, fit.root), "true_pose_": (truth.scales[0].numpy(), q, root)}
    for prefix, (scales, coords, roots) in cases.items():
        skin = fit_skin(model, scales, coords, roots, observed)
        mean_shape = skin.shape.copy()
        mean_shape[model.n_bone :] = 0.0
        for name, body in (("fit", skin), ("mean_identity", replace(skin, shape=mean_shape))):
            v = body.vertices(model, coords, roots)
            out[f"{prefix}{name}_mm"] = float(np.linalg.norm(v - true_v, axis=-1).mean() * 1000)
    return out


# Error-map colour bins (mm, upper edges) and their colours, light to dark.
ERROR_BINS = (0.5, 1.0, 2.0, 4.0, np.inf)
ERROR_COLOURS = (
    (0.85, 0.88, 0.92),
    (0.62, 0.78, 0.90),
    (0.98, 0.80, 0.45),
    (0.93, 0.50, 0.25),
    (0.70, 0.10, 0.12),
)


def _error_meshes(vertices: np.ndarray, faces: np.ndarray, error_mm: np.ndarray) -> list[Any]:
    """The skin (V, 3) split into one mesh per error bin of its faces (the worst of their vertices)."""
    from benchmarks.render import RenderMesh

    face_error = error_mm[faces].max(axis=1)
    lower = 0.0
    meshes = []
    for upper, colour in zip(ERROR_BINS, ERROR_COLOURS, strict=True):
        sel = (face_error >= lower) & (face_error < upper)
        if sel.any():
            meshes.append(RenderMesh(vertices, faces[sel], colour))
        lower = upper
    return meshes


def render_images(out: Path = ROOT / "docs", n: int = 3) -> list[Path]:
    """Held-out error maps (front and back): the first ``n`` held-out bodies' identity reconstructed by the
    spiral decoder (d = 8) and by the PCA of equal size."""
    from benchmarks.render import label_grid, render, save_png, tile
    from bodyfit.models.body.model import BodyModel
    from bodyfit.models.decoders.asset import load_asset
    from bodyfit.models.decoders.pipeline import default_work_dir, identity_sets
    from bodyfit.models.decoders.train import decode, fit_latents, pca_codes, pca_of

    torch.set_num_threads(1)
    model = BodyModel.load()
    pop = identity_sets(model, default_work_dir())["population"]
    asset = load_asset(8)
    pca = pca_of(pop.offsets[~pop.held], 8)
    offsets, c_bone = pop.offsets[pop.held][:n], pop.c_bone[pop.held][:n]
    init = pca_codes(pca, offsets)
    recon = {
        "spiral d=8": decode(asset.decoder, fit_latents(asset.decoder, offsets, init)),
        "PCA d=8": pca.reconstruct(init).reshape(offsets.shape),
    }
    template = model.data["vertices_mean"] + np.einsum("nk,kvc->nvc", c_bone, model.data["bone_correctives"])
    faces = model.faces
    images, titles = [], []
    for rec in recon.values():
        for b in range(n):
            error = np.linalg.norm(rec[b] - offsets[b], axis=-1) * 1e3
            skin = template[b] + offsets[b]
            for view in ("front", "back"):
                images.append(render(_error_meshes(skin, faces, error), view=view, size=(256, 384)))
            titles += [f"body {b + 1} front ({error.mean():.2f} mm)", f"body {b + 1} back"]
    grid = tile(images, 2 * n)
    caption = "per-vertex error, mm: <0.5 grey, <1 blue, <2 yellow, <4 orange, >=4 red"
    labelled = label_grid(grid, [titles[: 2 * n], titles[2 * n :]], list(recon), caption, font_size=14)
    path = out / "decoders_heldout_errors.png"
    save_png(labelled, path)
    return [path]


def main(argv: list[str] | None = None) -> None:
    from benchmarks.bench_cli import bench_main

    bench_main(
        run, "Spiral identity decoder against the identity PCA, and ONNX speed.", "50 held-out bodies", argv
    )


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    if sys.argv[1:] == ["images"]:
        print(render_images())
    else:
        main()

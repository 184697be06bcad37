"""The asset folder of a grown shape space: what ``BodyModel.load(folder)`` and ``bodyfit serve --assets
folder`` read.

The folder is a copy of the asset folder the space grew from, with ``body.npz`` replaced (the recomputed
shape space; faces, skinning weights, bind pose and landmarks unchanged), ``body.onnx`` exported from it, the
grow report beside them, and a manifest that hashes every file again and records where the space came from.
The skeleton, the bone meshes and the SMPL-topology and proxy files are the source's, byte for byte.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bodyfit.models.assets import MANIFEST, read_manifest, sha256, write_manifest
from bodyfit.models.body.model import BODY_ASSET, BodyModel
from bodyfit.models.body.onnx_export import BODY_ONNX, INPUTS, OUTPUTS, export_body_onnx
from bodyfit.models.errors import AssetError

REPORT = "grow_report.json"
GROWN_KEY = "grown_from"  # the manifest's record of the source folder: marks a folder this writer made


def check_destination(source: Path, out: Path) -> None:
    """Refuse to write into the source folder, or over a non-empty folder that is not a grown space (one
    whose manifest has :data:`GROWN_KEY`): a grown space never replaces other assets.

    Raises:
        AssetError: either case.
    """
    if out.resolve() == source.resolve():
        raise AssetError(f"{out} is the asset folder the space grows from; write the grown space elsewhere")
    if out.is_dir() and any(out.iterdir()):
        manifest = out / MANIFEST
        grown = False
        if manifest.is_file():
            try:
                grown = GROWN_KEY in json.loads(manifest.read_text())
            except json.JSONDecodeError:
                grown = False
        if not grown:
            raise AssetError(
                f"{out} is not empty and holds no grown shape space; give an empty or new folder"
            )


def write_space(
    source: Path, out: Path, model: BodyModel, data: dict[str, np.ndarray], report: dict[str, Any]
) -> Path:
    """Write the grown space ``data`` (``body.npz`` arrays on ``model``'s skeleton, loaded from ``source``)
    as a complete asset folder ``out`` with ``report`` (:data:`REPORT`); returns ``out``.

    Raises:
        AssetError: ``out`` is refused (:func:`check_destination`) or the source's manifest is unreadable.
    """
    check_destination(source, out)
    manifest = read_manifest(source)
    out.mkdir(parents=True, exist_ok=True)
    entries: dict[str, dict[str, Any]] = {}
    for name, entry in manifest.get("files", {}).items():
        if name in (BODY_ASSET, BODY_ONNX):
            continue
        shutil.copyfile(source / name, out / name)
        entries[name] = {k: v for k, v in entry.items() if k not in ("sha256", "bytes")}
    (out / MANIFEST).unlink(missing_ok=True)
    np.savez_compressed(out / BODY_ASSET, allow_pickle=False, **data)
    grown = BodyModel(model.skeleton, data)
    export_body_onnx(grown.decoder(torch.float32), grown.n_shape, out / BODY_ONNX)
    (out / REPORT).write_text(json.dumps(report, indent=1) + "\n")
    entries[BODY_ASSET] = {
        "vertices": grown.n_vertices,
        "faces": len(grown.faces),
        "bone_coefficients": grown.n_bone,
        "identity_coefficients": grown.n_identity,
    }
    entries[BODY_ONNX] = {"inputs": list(INPUTS), "outputs": list(OUTPUTS), "opset": 18}
    entries[REPORT] = {}
    info = {k: v for k, v in manifest.items() if k != "files"}
    info[GROWN_KEY] = {
        "folder": str(source.resolve()),
        "body_sha256": sha256(source / BODY_ASSET),
        "accepted": report.get("n_accepted", 0),
        "rounds": report.get("n_rounds", 0),
    }
    write_manifest(out, entries, info)
    BodyModel.load(out)  # the folder must load as it will be served: hash-checked
    return out

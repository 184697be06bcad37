"""JSON encodings shared by the REST routes: arrays (dtype, shape, base64 little-endian bytes) and the
results of fits, so that clients get exact float values without parsing huge number lists."""

from __future__ import annotations

import base64
from typing import Any

import numpy as np

from bodyfit.models.fitting.sequence.fitter import SequenceFit
from bodyfit.models.upgrade.upgrade import UpgradeResult
from bodyfit.service.core import MeshFit
from bodyfit.service.jobs import Progress

WIRE_DTYPES = ("float32", "float64", "int32", "int64", "bool")


def encode_array(a: np.ndarray) -> dict[str, Any]:
    """``{"dtype", "shape", "data"}`` with ``data`` the base64 of the little-endian C-order bytes."""
    arr = np.ascontiguousarray(a)
    if arr.dtype.name not in WIRE_DTYPES:
        arr = arr.astype(np.float64 if arr.dtype.kind == "f" else np.int64)
    return {
        "dtype": arr.dtype.name,
        "shape": list(arr.shape),
        "data": base64.b64encode(arr.astype(arr.dtype.newbyteorder("<")).tobytes()).decode(),
    }


def progress_event(p: Progress) -> dict[str, Any]:
    return {"event": "progress", **p.to_dict()}


def mesh_fit_result(fit: MeshFit, dof_names: list[str], joint_names: list[str]) -> dict[str, Any]:
    """The final event of a scan / mesh fit."""
    return {
        "event": "result",
        "fitted_as": fit.fitted_as,
        "dof_names": dof_names,
        "joint_names": joint_names,
        "arrays": {k: encode_array(np.asarray(v, np.float32)) for k, v in fit.arrays().items()},
        "report": fit.report.to_dict(),
    }


def sequence_chunks(fit: SequenceFit, chunk: int) -> list[dict[str, Any]]:
    """Per-chunk events of a sequence fit: frames ``[start, stop)`` with coordinates, root, vertices,
    joints and per-frame mean error (mm)."""
    events = []
    for lo in range(0, len(fit.coordinates), chunk):
        hi = min(len(fit.coordinates), lo + chunk)
        errors = np.array([r.distances.mean for r in fit.reports[lo:hi]])
        events.append(
            {
                "event": "chunk",
                "start": lo,
                "stop": hi,
                "arrays": {
                    "coordinates": encode_array(fit.coordinates[lo:hi]),
                    "root": encode_array(fit.root[lo:hi]),
                    "vertices": encode_array(fit.registration(lo, hi)),
                    "joints": encode_array(fit.joints[lo:hi].astype(np.float32)),
                    "error_mm": encode_array(errors),
                },
            }
        )
    return events


def sequence_summary(fit: SequenceFit, joint_names: list[str]) -> dict[str, Any]:
    """The final event of a sequence fit (the per-frame arrays came in the chunks)."""
    return {
        "event": "result",
        "dof_names": list(fit.dof_names),
        "joint_names": joint_names,
        "arrays": {"shape": encode_array(fit.shape)},
        "stats": fit.stats.to_dict(),
        "limit_violations": sum(r.limit_violations for r in fit.reports),
        "confident_frames": sum(r.confident for r in fit.reports),
    }


def upgrade_chunks(result: UpgradeResult, chunk: int) -> list[dict[str, Any]]:
    """Per-chunk events of an upgrade: frames ``[start, stop)`` with coordinates, root, joints, per-frame
    error (mm) and bad-frame flags."""
    events = []
    for lo in range(0, len(result.coordinates), chunk):
        hi = min(len(result.coordinates), lo + chunk)
        arrays = {
            "coordinates": result.coordinates[lo:hi],
            "root": result.root[lo:hi],
            "joints": result.joints[lo:hi].astype(np.float32),
            "error_mm": result.error_mm[lo:hi],
            "bad_frames": result.bad_frames[lo:hi],
        }
        events.append(
            {
                "event": "chunk",
                "start": lo,
                "stop": hi,
                "arrays": {k: encode_array(v) for k, v in arrays.items()},
            }
        )
    return events


def upgrade_summary(result: UpgradeResult, files: dict[str, bytes]) -> dict[str, Any]:
    """The final event of an upgrade: names, shape and bone scales, the summary, and the files (base64)."""
    return {
        "event": "result",
        "dof_names": list(result.dof_names),
        "joint_names": list(result.joint_names),
        "segment_names": list(result.segment_names),
        "arrays": {"shape": encode_array(result.shape), "scales": encode_array(result.scales)},
        "summary": result.summary(),
        "files": {ext: base64.b64encode(data).decode() for ext, data in files.items()},
    }

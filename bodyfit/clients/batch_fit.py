"""Batch fits of a folder of scans: resumable, concurrent, one failure never stops the rest.

``batch_fit(scans_dir, out_dir, concurrency=N, backend=...)`` walks ``scans_dir`` for scan files (ply, obj,
stl, pcd, npz: :data:`~bodyfit.clients.uploads.SCAN_FORMATS`), fits each one and writes
``<out_dir>/<same relative path without extension>`` ``.npz`` (shape, coordinates, root, vertices, joints,
to_model, dof_names, joint_names, fitted_as), ``.ply`` (the registration in the scan's frame) and ``.json``
(the fit report with ``scan`` and ``fitted_as``; written last: its presence marks a finished scan, so an
interrupted run resumes where it stopped). The back-end is a server URL (``"http://host:8000"``: the REST
SDK, ``concurrency`` requests at once) or any :class:`~bodyfit.clients.batch.Worker`; fitting in this
process or on Ray needs the service and the models, which the SDK does not import: those back-ends are
:func:`bodyfit.cli.backends.fitter` (``"local"``, ``"ray"``, ``"ray://host:10001"``), as ``bodyfit
batch-fit --backend`` runs them.
"""

from __future__ import annotations

import io
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from bodyfit.clients.batch import BatchReport, Files, Worker, run_batch
from bodyfit.clients.uploads import SCAN_FORMATS

FIT_OPTIONS = ("units", "up", "facing", "pose", "sex", "height_m")
"""The per-scan options of a fit (:meth:`bodyfit.clients.RestClient.fit_scan`'s units and hints)."""


def find_scans(scans_dir: Path) -> list[Path]:
    """Every scan file under ``scans_dir`` (a :data:`SCAN_FORMATS` extension, any case; hidden files and
    folders skipped), sorted.

    Raises:
        ValueError: two scans that would write the same outputs (same relative path but the extension,
            e.g. a.ply and a.obj); rename one.
    """
    scans = sorted(
        p
        for p in scans_dir.rglob("*")
        if p.is_file()
        and p.suffix.lower().lstrip(".") in SCAN_FORMATS
        and not any(part.startswith(".") for part in p.relative_to(scans_dir).parts)
    )
    seen: dict[Path, Path] = {}
    for path in scans:
        base = path.relative_to(scans_dir).with_suffix("")
        if base in seen:
            raise ValueError(
                f"{seen[base]} and {path} would both write {base}.npz/.ply/.json: rename one of them"
            )
        seen[base] = path
    return scans


def ply_bytes(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    """A binary little-endian PLY of a triangle mesh: vertices (V, 3) float32, faces (F, 3)."""
    v = np.ascontiguousarray(vertices, dtype="<f4")
    f = np.empty(len(faces), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    f["n"], f["idx"] = 3, faces
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    return header.encode("ascii") + v.tobytes() + f.tobytes()


def fit_files(
    scan: str,
    fitted_as: str,
    arrays: Mapping[str, np.ndarray | None],
    dof_names: Sequence[str],
    joint_names: Sequence[str],
    report: Mapping[str, Any],
    faces: np.ndarray | None,
) -> Files:
    """One fit's output files: ``npz`` (``arrays``: shape, coordinates, root, vertices, joints, to_model;
    plus the names and ``fitted_as``), ``json`` (``report`` with ``scan`` and ``fitted_as``) and, with the
    model's ``faces`` (F, 3), ``ply`` (the registration ``arrays["vertices"]`` (V, 3))."""
    buffer = io.BytesIO()
    np.savez_compressed(
        buffer,
        allow_pickle=False,
        **{k: np.asarray(v) for k, v in arrays.items() if v is not None},
        dof_names=np.array(dof_names),
        joint_names=np.array(joint_names),
        fitted_as=np.array(fitted_as),
    )
    files = {"npz": buffer.getvalue()}
    if faces is not None:
        files["ply"] = ply_bytes(np.asarray(arrays["vertices"]), faces)
    record = {"scan": scan, "fitted_as": fitted_as, **report}
    files["json"] = (json.dumps(record, indent=1) + "\n").encode()
    return files


def server_fitter(url: str, timeout: float = 600.0, **options: Any) -> Worker:
    """Fits through a bodyfit server's REST API, every scan with the same ``options`` (:data:`FIT_OPTIONS`:
    units and the hints); the model's faces for the registration meshes are asked for once."""
    import httpx

    from bodyfit.clients.rest_client import Client

    client = Client(url, timeout=httpx.Timeout(30.0, read=timeout))
    faces: list[np.ndarray] = []

    def fit(path: Path) -> Files:
        result = client.fit_scan(path, **options)
        if not faces:
            faces.append(np.asarray(client.synthesize(faces=True).faces))
        arrays = {
            "shape": result.shape,
            "coordinates": result.coordinates,
            "root": result.root,
            "vertices": result.vertices,
            "joints": result.joints,
            "to_model": result.to_model,
        }
        return fit_files(
            path.name, result.fitted_as, arrays, result.dof_names, result.joint_names, result.report, faces[0]
        )

    return fit


def batch_fit(
    scans_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    concurrency: int = 1,
    backend: str | Worker = "http://127.0.0.1:8000",
    progress: bool = True,
    **options: Any,
) -> BatchReport:
    """Fit every scan under ``scans_dir`` into ``out_dir`` (see the module docstring).

    Args:
        concurrency: scans in flight at once (requests or threads).
        backend: a server URL or any :class:`~bodyfit.clients.batch.Worker` callable (a path in, its files
            out; :func:`bodyfit.cli.backends.fitter` builds the in-process and Ray ones).
        progress: show a tqdm bar.
        options: :data:`FIT_OPTIONS` for every scan, with a server URL back-end (units: auto, m or mm; the
            hints up, facing, pose, sex, height_m; see ``fit_scan``).

    Raises:
        FileNotFoundError: ``scans_dir`` is not a folder.
        ValueError: an unknown option, options with a callable back-end (it applies its own), or two scans
            that would write the same outputs.
    """
    root = Path(scans_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"{root} is not a folder of scans ({', '.join(SCAN_FORMATS)} files)")
    unknown = sorted(set(options) - set(FIT_OPTIONS))
    if unknown:
        allowed = ", ".join(FIT_OPTIONS)
        raise ValueError(f"unknown batch_fit option(s) {', '.join(unknown)}; allowed: {allowed}")
    if isinstance(backend, str):
        if not backend.startswith(("http://", "https://")):
            raise ValueError(
                f"backend {backend!r} is not a server URL (http://host:8000); in-process and Ray back-ends: "
                "bodyfit.cli.backends.fitter(name, concurrency)"
            )
        worker = server_fitter(backend, **options)
    elif options:
        given = ", ".join(sorted(options))
        raise ValueError(f"{given} need a server URL back-end; a callable back-end applies its own")
    else:
        worker = backend
    return run_batch(root, Path(out_dir), find_scans(root), worker, concurrency, progress, "scan", "fitted")

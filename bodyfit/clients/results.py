"""What the SDK returns: numpy results decoded from the wire (shared by the REST and gRPC clients)."""

from __future__ import annotations

import base64
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bodyfit.clients.errors import ServerError, error_from_problem
from bodyfit.io.errors import FileFormatError, FileLimitError
from bodyfit.io.npz import FLOAT, INTEGER, TEXT, ArraySpec, Dim, read_npz

ProgressCallback = Callable[[dict[str, Any]], None]
"""Called with each progress event: ``{"stage", "done", "total", "message"}``."""


def decode_array(doc: dict[str, Any] | np.ndarray) -> np.ndarray:
    """The inverse of the server's array encoding ``{"dtype", "shape", "data": base64 little-endian}``
    (an array already decoded, as the gRPC transport gives, is returned as it is)."""
    if isinstance(doc, np.ndarray):
        return doc
    dtype = np.dtype(str(doc["dtype"])).newbyteorder("<")
    return (
        np.frombuffer(base64.b64decode(doc["data"]), dtype=dtype)
        .reshape(doc["shape"])
        .astype(dtype.newbyteorder("="))
    )


@dataclass(frozen=True)
class ModelInfo:
    """dof_names, dof_ranges (n_dof, 2), dof_units ("rad" / "m"); shape counts; mesh sizes; joint names;
    the asset version and per-file sha256."""

    dof_names: tuple[str, ...]
    dof_ranges: np.ndarray
    dof_units: tuple[str, ...]
    n_bone: int
    n_identity: int
    n_vertices: int
    n_faces: int
    joint_names: tuple[str, ...]
    assets: dict[str, Any]
    version: str

    @property
    def n_shape(self) -> int:
        return self.n_bone + self.n_identity

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> ModelInfo:
        dofs = doc["dofs"]
        return cls(
            dof_names=tuple(d["name"] for d in dofs),
            dof_ranges=np.array([[d["min"], d["max"]] for d in dofs], np.float64),
            dof_units=tuple(d["unit"] for d in dofs),
            n_bone=int(doc["shape"]["n_bone"]),
            n_identity=int(doc["shape"]["n_identity"]),
            n_vertices=int(doc["mesh"]["n_vertices"]),
            n_faces=int(doc["mesh"]["n_faces"]),
            joint_names=tuple(doc["joint_names"]),
            assets=dict(doc["assets"]),
            version=str(doc["version"]),
        )


@dataclass(frozen=True)
class Synthesis:
    """vertices (B, V, 3) and joints (B, J, 3) float32 metres; faces (F, 3) when asked for; bones
    (B, Vb, 3) and bone_faces when the skeleton was asked for."""

    vertices: np.ndarray
    joints: np.ndarray
    joint_names: tuple[str, ...]
    faces: np.ndarray | None = None
    bones: np.ndarray | None = None
    bone_faces: np.ndarray | None = None

    @classmethod
    def from_npz(cls, data: bytes) -> Synthesis:
        """Decode the server's npz answer, each array checked from its .npy header before it is built.

        Raises:
            ServerError: an answer that is not the npz the server sends (truncated, wrong arrays).
        """
        return cls.from_event(synthesis_event(data))

    @classmethod
    def from_event(cls, doc: dict[str, Any]) -> Synthesis:
        """From ``{"arrays": {vertices, joints[, faces, bones, bone_faces]}, "joint_names"}``."""
        a = {k: decode_array(v) for k, v in doc["arrays"].items()}
        names = tuple(str(n) for n in doc["joint_names"])
        return cls(a["vertices"], a["joints"], names, a.get("faces"), a.get("bones"), a.get("bone_faces"))


def synthesis_event(data: bytes) -> dict[str, Any]:
    """The server's npz answer to a synthesis as ``{"arrays", "joint_names"}``, each array checked from
    its .npy header before it is built.

    Raises:
        ServerError: an answer that is not the npz the server sends (truncated, wrong arrays).
    """
    B, J = Dim("B"), Dim("J")
    specs = {
        "vertices": ArraySpec(((B, Dim("V"), 3),), FLOAT),
        "joints": ArraySpec(((B, J, 3),), FLOAT),
        "joint_names": ArraySpec(((J,),), TEXT),
        "faces": ArraySpec(((Dim("F"), 3),), INTEGER, required=False),
        "bones": ArraySpec(((B, Dim("Vb"), 3),), FLOAT, required=False),
        "bone_faces": ArraySpec(((Dim("Fb"), 3),), INTEGER, required=False),
    }
    try:
        arrays = dict(read_npz(data, specs, name="the server's answer"))
    except (FileFormatError, FileLimitError) as exc:
        raise ServerError(f"unreadable synthesis answer: {exc}") from None
    return {"joint_names": arrays.pop("joint_names").tolist(), "arrays": arrays}


@dataclass(frozen=True)
class MeshFitResult:
    """One fitted mesh or scan: ``fitted_as`` ("registered", "SMPL topology", "raw scan"); shape
    (n_shape,), coordinates (n_dof,) named by ``dof_names``, root (3,), the registration ``vertices``
    (V, 3) in the model's topology, ``joints`` (J, 3); ``report``: distances (mm), limit violations,
    iterations, seconds, confident and the reasons when not."""

    fitted_as: str
    shape: np.ndarray
    coordinates: np.ndarray
    root: np.ndarray
    vertices: np.ndarray
    joints: np.ndarray
    dof_names: tuple[str, ...]
    joint_names: tuple[str, ...]
    report: dict[str, Any]

    @property
    def confident(self) -> bool:
        return bool(self.report.get("confident"))

    @classmethod
    def from_event(cls, doc: dict[str, Any]) -> MeshFitResult:
        a = {k: decode_array(v) for k, v in doc["arrays"].items()}
        return cls(
            str(doc["fitted_as"]),
            a["shape"],
            a["coordinates"],
            a["root"],
            a["vertices"],
            a["joints"],
            tuple(doc["dof_names"]),
            tuple(doc["joint_names"]),
            dict(doc["report"]),
        )


@dataclass(frozen=True)
class SequenceResult:
    """A fitted sequence of T frames: shape (n_shape,); coordinates (T, n_dof); root (T, 3); vertices
    (T, V, 3); joints (T, J, 3); error_mm (T,) per-frame mean distance; stats (fps, jitter, ...)."""

    shape: np.ndarray
    coordinates: np.ndarray
    root: np.ndarray
    vertices: np.ndarray
    joints: np.ndarray
    error_mm: np.ndarray
    dof_names: tuple[str, ...]
    joint_names: tuple[str, ...]
    stats: dict[str, Any] = field(default_factory=dict)
    limit_violations: int = 0

    @classmethod
    def from_events(cls, chunks: list[dict[str, Any]], result: dict[str, Any]) -> SequenceResult:
        arrays = per_frame(chunks, ("coordinates", "root", "vertices", "joints", "error_mm"))
        return cls(
            shape=decode_array(result["arrays"]["shape"]),
            dof_names=tuple(result["dof_names"]),
            joint_names=tuple(result["joint_names"]),
            stats=dict(result.get("stats", {})),
            limit_violations=int(result.get("limit_violations", 0)),
            **arrays,
        )


def per_frame(chunks: list[dict[str, Any]], keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The per-frame arrays ``keys`` of a stream's chunk events, joined in frame order (by ``start``)."""
    ordered = sorted(chunks, key=lambda c: int(c["start"]))
    return {key: np.concatenate([decode_array(c["arrays"][key]) for c in ordered]) for key in keys}


class EventCollector:
    """Consumes a stream of events: forwards progress, keeps chunks, raises the typed error of an
    ``error`` event; :meth:`feed` returns True at the ``result`` event."""

    def __init__(self, progress: ProgressCallback | None) -> None:
        self.progress = progress
        self.chunks: list[dict[str, Any]] = []
        self.result: dict[str, Any] | None = None
        self.events = 0

    def feed(self, event: dict[str, Any]) -> bool:
        self.events += 1
        kind = event.get("event")
        if kind == "progress" and self.progress is not None:
            self.progress({k: v for k, v in event.items() if k != "event"})
        elif kind == "chunk":
            self.chunks.append(event)
        elif kind == "error":
            raise error_from_problem(event, event.get("status"))
        elif kind == "result":
            self.result = event
        return self.result is not None

    def finish(self) -> tuple[list[dict[str, Any]], dict[str, Any]]:
        """(chunks, result)."""
        if self.result is None:
            raise ServerError("the server's stream ended without a result (the connection was cut?)")
        return self.chunks, self.result


@dataclass(frozen=True)
class UpgradeOutput:
    """An upgraded SMPL-format sequence of T frames: coordinates (T, n_dof) named by ``dof_names``; root
    (T, 3); joints (T, J, 3); error_mm (T,) per frame; bad_frames (T,); shape (n_shape,); scales (n_seg, 3);
    summary (path, v2v, frames/s, limit violations, largest frame jump, notes); files: the server's npz,
    json, osim and mot as bytes (:meth:`save` writes them)."""

    coordinates: np.ndarray
    root: np.ndarray
    joints: np.ndarray
    error_mm: np.ndarray
    bad_frames: np.ndarray
    shape: np.ndarray
    scales: np.ndarray
    dof_names: tuple[str, ...]
    joint_names: tuple[str, ...]
    summary: dict[str, Any]
    files: dict[str, bytes]

    def save(self, folder: str | Path, name: str) -> dict[str, Path]:
        """Write ``name``.npz / .json / .osim / .mot into ``folder``; returns the paths."""
        out = Path(folder)
        out.mkdir(parents=True, exist_ok=True)
        paths = {}
        for ext, data in self.files.items():
            paths[ext] = out / f"{name}.{ext}"
            paths[ext].write_bytes(data)
        return paths

    @classmethod
    def from_events(cls, chunks: list[dict[str, Any]], result: dict[str, Any]) -> UpgradeOutput:
        arrays = per_frame(chunks, ("coordinates", "root", "joints", "error_mm", "bad_frames"))
        return cls(
            shape=decode_array(result["arrays"]["shape"]),
            scales=decode_array(result["arrays"]["scales"]),
            dof_names=tuple(result["dof_names"]),
            joint_names=tuple(result["joint_names"]),
            summary=dict(result["summary"]),
            files={ext: _file_bytes(data) for ext, data in result["files"].items()},
            **arrays,
        )


def _file_bytes(data: str | bytes) -> bytes:
    """A file of an upgrade: base64 text in JSON, bytes over gRPC."""
    return bytes(data) if isinstance(data, bytes | bytearray) else base64.b64decode(data)

"""What the SDK returns: numpy results read from the server's answers (shared by the REST and gRPC
clients). The answers are read with the models of :mod:`bodyfit.wire`; an answer that does not match them
raises :class:`~bodyfit.clients.errors.ServerError` saying where."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from pydantic import TypeAdapter, ValidationError

from bodyfit import wire as w
from bodyfit.clients.errors import ServerError, error_from_problem, error_from_validation
from bodyfit.io.errors import FileFormatError, FileLimitError
from bodyfit.io.npz import FLOAT, INTEGER, TEXT, ArraySpec, Dim, read_npz
from bodyfit.wire import ModelInfo  # the SDK's model info is the wire's
from bodyfit.wire.measure import Measurements
from bodyfit.wire.subjects import SubjectResult

ProgressCallback = Callable[[dict[str, Any]], None]
"""Called with each progress event: ``{"stage", "done", "total", "message"}``."""
T = TypeVar("T")
Document = str | bytes | dict[str, Any]
"""An answer as the transport has it: JSON text (REST) or a dict of Python values (gRPC)."""


def reader(adapter: TypeAdapter[T], what: str) -> Callable[[Document], T]:
    """A function reading a document with ``adapter`` (JSON text or Python values).

    The function raises ServerError when the document does not match (its message names the keys at fault).
    """

    def read(doc: Document) -> T:
        try:
            if isinstance(doc, str | bytes):
                return adapter.validate_json(doc)
            return adapter.validate_python(doc)
        except ValidationError as exc:
            raise error_from_validation(exc, what) from None

    return read


read_model_info = reader(TypeAdapter(ModelInfo), "model info")
read_measurements = reader(TypeAdapter(Measurements), "measurements")


def decode_array(doc: w.WireArray | dict[str, Any] | np.ndarray) -> np.ndarray:
    """The numpy array of a wire array (a :class:`~bodyfit.wire.WireArray` or its document); an array
    already decoded is returned as it is.

    Raises:
        ServerError: a document that is not a wire array (unknown dtype, a byte count that does not
            match dtype and shape, ...).
    """
    if isinstance(doc, np.ndarray):
        return doc
    if isinstance(doc, w.WireArray):
        return doc.to_numpy()
    return _read_array(doc).to_numpy()


_read_array = reader(TypeAdapter(w.WireArray), "array")


@dataclass(frozen=True)
class Synthesis:
    """vertices (B, V, 3) and joints (B, J, 3) float32 metres; faces (F, 3) when asked for; bones
    (B, Vb, 3) and bone_faces when the skeleton was asked for; ``built``, for bodies built from
    measurements, what was requested and achieved (its ``shape``, ``requested``, ``values``,
    ``residuals``, ``unmet``)."""

    vertices: np.ndarray
    joints: np.ndarray
    joint_names: tuple[str, ...]
    faces: np.ndarray | None = None
    bones: np.ndarray | None = None
    bone_faces: np.ndarray | None = None
    built: Measurements | None = None

    @classmethod
    def from_npz(cls, data: bytes) -> Synthesis:
        """Decode the server's npz answer, each array checked from its .npy header before it is built.

        Raises:
            ServerError: an answer that is not the npz the server sends (truncated, wrong arrays).
        """
        return cls.from_event(synthesis_event(data))

    @classmethod
    def from_event(cls, doc: dict[str, Any]) -> Synthesis:
        """From ``{"arrays": {vertices, joints[, faces, bones, bone_faces]}, "joint_names"[, "built"]}``,
        the arrays numpy arrays or wire arrays, ``built`` a measurements document (JSON text or values).

        Raises:
            ServerError: vertices or joints missing, an array that is not a wire array, or a ``built``
                that is not a measurements document.
        """
        a = {k: decode_array(v) for k, v in doc.get("arrays", {}).items()}
        if "vertices" not in a or "joints" not in a:
            raise ServerError(f"the server's synthesis holds {sorted(a)}, without vertices and joints")
        names = tuple(str(n) for n in doc.get("joint_names", ()))
        built = doc.get("built")
        return cls(
            a["vertices"],
            a["joints"],
            names,
            a.get("faces"),
            a.get("bones"),
            a.get("bone_faces"),
            None if built is None else read_measurements(built),
        )


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
    (V, 3) in the model's topology, ``joints`` (J, 3); ``report``: distances (mm; for raw scans both ways,
    see :class:`bodyfit.wire.FitReport`), limit violations, iterations, seconds, confident and the reasons
    when not, and under ``extra["hints"]`` how each hint was used. ``vertices`` and ``joints`` lie in the
    input's frame; ``to_model`` (4, 4) maps it to the frame the parameters pose the model in (None from a
    server older than the field)."""

    fitted_as: str
    shape: np.ndarray
    coordinates: np.ndarray
    root: np.ndarray
    vertices: np.ndarray
    joints: np.ndarray
    dof_names: tuple[str, ...]
    joint_names: tuple[str, ...]
    report: dict[str, Any]
    to_model: np.ndarray | None = None

    @property
    def confident(self) -> bool:
        return bool(self.report.get("confident"))

    @property
    def predicted_error_mm(self) -> float | None:
        """Raw scans: the report's calibrated predicted registration error (mm), which ``confident``
        follows; None where the server did not estimate it."""
        value = self.report.get("predicted_error_mm")
        return None if value is None else float(value)

    @classmethod
    def from_event(cls, doc: w.MeshFit) -> MeshFitResult:
        a = doc.arrays
        return cls(
            doc.fitted_as,
            a.shape.to_numpy(),
            a.coordinates.to_numpy(),
            a.root.to_numpy(),
            a.vertices.to_numpy(),
            a.joints.to_numpy(),
            doc.dof_names,
            doc.joint_names,
            doc.report.model_dump(mode="json"),
            None if a.to_model is None else a.to_model.to_numpy(),
        )


@dataclass(frozen=True)
class SequenceResult:
    """A fitted sequence of T frames: shape (n_shape,); coordinates (T, n_dof); root (T, 3); vertices
    (T, V, 3); joints (T, J, 3); error_mm (T,) per-frame mean distance; stats (fps, jitter, ...);
    confident_frames: how many frames' fits the server reports confident (None from a server that does not
    say)."""

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
    confident_frames: int | None = None

    @classmethod
    def from_events(cls, chunks: Sequence[w.SequenceChunk], result: w.SequenceFit) -> SequenceResult:
        """Raises ServerError when the chunks do not cover the frames once each, in order."""
        arrays = per_frame(chunks, ("coordinates", "root", "vertices", "joints", "error_mm"))
        return cls(
            shape=result.arrays.shape.to_numpy(),
            dof_names=result.dof_names,
            joint_names=result.joint_names,
            stats=result.stats.model_dump(mode="json"),
            limit_violations=result.limit_violations,
            confident_frames=result.confident_frames,
            **arrays,
        )


def per_frame(
    chunks: Sequence[w.SequenceChunk | w.UpgradeChunk], keys: tuple[str, ...]
) -> dict[str, np.ndarray]:
    """The per-frame arrays ``keys`` of a stream's chunk events, joined in frame order (by ``start``).

    Raises:
        ServerError: no chunks, chunks that leave out or repeat frames, or whose arrays do not hold
            ``stop - start`` frames.
    """
    ordered = sorted(chunks, key=lambda c: c.start)
    if not ordered:
        raise ServerError("the server's stream has no chunk of frames")
    stop = 0
    for c in ordered:
        if c.start != stop:
            raise ServerError(
                f"the server's chunks are not contiguous: frames [{c.start}, {c.stop}) follow frame {stop}"
            )
        stop = c.stop
    out = {}
    for key in keys:
        parts = [getattr(c.arrays, key) for c in ordered]
        for c, a in zip(ordered, parts, strict=True):
            if not a.shape or a.shape[0] != c.stop - c.start:
                raise ServerError(
                    f"the server's chunk [{c.start}, {c.stop}) has {key} of shape {list(a.shape)}, not "
                    f"{c.stop - c.start} frames"
                )
        out[key] = np.concatenate([a.to_numpy() for a in parts])
    return out


class EventCollector:
    """Consumes the documents of an answer, each read by ``parse``: forwards progress, keeps chunks,
    raises the typed error of an ``error`` event; :meth:`feed` returns True at the result (a unary
    answer's only document)."""

    def __init__(self, progress: ProgressCallback | None, parse: Callable[[Any], Any]) -> None:
        self.progress = progress
        self.parse = parse
        self.chunks: list[w.FrameChunk] = []
        self.result: Any = None
        self.events = 0

    def feed(self, doc: Any) -> bool:
        """Returns True at the result; raises ServerError for a document that is not what the server
        sends, or the typed error of an ``error`` event."""
        self.events += 1
        event = self.parse(doc)
        if isinstance(event, w.ProgressEvent):
            if self.progress is not None:
                self.progress(event.model_dump(mode="json", exclude={"event"}))
        elif isinstance(event, w.ErrorEvent):
            raise error_from_problem(event.model_dump(mode="json", exclude_none=True), event.status)
        elif isinstance(event, w.FrameChunk):
            self.chunks.append(event)
        else:
            self.result = event
            return True
        return False

    def finish(self) -> tuple[list[w.FrameChunk], Any]:
        """(chunks, result)."""
        if self.result is None:
            raise ServerError("the server's stream ended without a result (the connection was cut?)")
        return self.chunks, self.result


@dataclass(frozen=True)
class UpgradeOutput:
    """An upgraded SMPL-format sequence of T frames: coordinates (T, n_dof) named by ``dof_names``; root
    (T, 3); joints (T, J, 3); error_mm (T,) per frame; bad_frames (T,); shape (n_shape,); scales (n_seg, 3),
    one row per ``segment_names``; summary (path, v2v, frames/s, limit violations, largest frame jump,
    notes); files: the server's npz, json, osim and mot as bytes (:meth:`save` writes them)."""

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
    segment_names: tuple[str, ...] = ()

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
    def from_events(cls, chunks: Sequence[w.UpgradeChunk], result: w.UpgradeResult) -> UpgradeOutput:
        """Raises ServerError when the chunks do not cover the frames once each, in order."""
        arrays = per_frame(chunks, ("coordinates", "root", "joints", "error_mm", "bad_frames"))
        return cls(
            shape=result.arrays.shape.to_numpy(),
            scales=result.arrays.scales.to_numpy(),
            dof_names=result.dof_names,
            joint_names=result.joint_names,
            segment_names=result.segment_names,
            summary=result.summary.model_dump(mode="json"),
            files=dict(result.files),
            **arrays,
        )


@dataclass(frozen=True)
class SubjectOutput:
    """One person's rig (``POST /v1/subjects``): the scans it was built from, each one's mean vertex error
    (mm) under the generic model and under the rig, the limb joints the poses left undetermined, the build's
    seconds, and ``subject``: the subject file's bytes (:meth:`save` writes it)."""

    scans: tuple[str, ...]
    generic_mm: tuple[float, ...]
    personal_mm: tuple[float, ...]
    undetermined_joints: tuple[str, ...]
    seconds: float
    subject: bytes

    def save(self, path: str | Path) -> Path:
        """Write the subject file (an ``.npz``) to ``path``; returns it."""
        target = Path(path)
        target.write_bytes(self.subject)
        return target

    @classmethod
    def from_event(cls, doc: SubjectResult) -> SubjectOutput:
        return cls(
            doc.scans, doc.generic_mm, doc.personal_mm, doc.undetermined_joints, doc.seconds, doc.subject
        )

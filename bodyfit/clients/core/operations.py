"""The SDK's operations, transport-neutral: each public method builds an :class:`Operation` here (its
arguments checked and normalised once, for REST and gRPC alike) that reads the transport's documents with
the models of :mod:`bodyfit.wire` and turns them into the result types of :mod:`bodyfit.clients.results`.

A transport yields an answer's documents as it has them (:data:`Event`): JSON text (REST: an NDJSON line,
a JSON body) or a dict of Python values (gRPC messages, arrays with raw bytes); a stream's events are
``progress``, ``chunk``, ``result`` or ``error``; a unary call answers one document.
"""

from __future__ import annotations

import io
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, TypeVar

import numpy as np

from bodyfit import wire as w
from bodyfit.clients.results import (
    Document,
    MeshFitResult,
    ModelInfo,
    ProgressCallback,
    SequenceResult,
    SubjectOutput,
    Synthesis,
    UpgradeOutput,
    read_measurements,
    read_model_info,
    reader,
)
from bodyfit.clients.uploads import ScanInput, SubjectInput, scan_upload, subject_upload
from bodyfit.wire.hints import axis_name, pose_class
from bodyfit.wire.measure import Measurements
from bodyfit.wire.subjects import SUBJECT_EVENTS, SubjectResult

R = TypeVar("R")
Event = Document
"""One document of an answer, as the transport has it: JSON text or a dict of Python values."""
Array = np.ndarray | None
Coordinates = np.ndarray | Mapping[str, float | Sequence[float] | np.ndarray] | None
SequenceInput = str | os.PathLike[str] | bytes
FORMATS = ("npz", "ply", "obj", "glb", "json")
"""The file formats of :meth:`synthesize_file`."""


@dataclass(frozen=True)
class Operation(Generic[R]):
    """One call: ``name`` (model_info, synthesize, fit_scan, fit_sequence, upgrade), ``parse`` reading
    each document of the answer (into a :mod:`bodyfit.wire` model), ``finish``: (chunk events, result) ->
    the result; its checked ``args``, whether sending it twice is harmless (``idempotent``), whether the
    server streams events (``stream``), and the ``progress`` callback."""

    name: str
    parse: Callable[[Event], Any]
    finish: Callable[[list[Any], Any], R]
    args: dict[str, Any] = field(default_factory=dict)
    idempotent: bool = False
    stream: bool = False
    progress: ProgressCallback | None = None


def _rows(a: np.ndarray | None) -> np.ndarray | None:
    return None if a is None else np.atleast_2d(np.asarray(a, np.float64))


def synthesis_args(
    shape: Array,
    coordinates: Coordinates,
    root: Array,
    skeleton: bool,
    faces: bool,
    batch: int | None,
    fmt: str,
    measurements: Mapping[str, float] | None = None,
    sex: str | None = None,
    subject: SubjectInput | None = None,
) -> dict[str, Any]:
    """The checked arguments of a synthesis: arrays as float64 rows, named coordinates as float64 arrays,
    measurements as {str: float}, the subject file as bytes.

    Raises:
        ValueError: a format other than :data:`FORMATS`, or more than one of shape, measurements and
            subject."""
    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {', '.join(FORMATS)}; got {fmt!r}")
    if shape is not None and measurements is not None:
        raise ValueError("give shape or measurements, not both: the body built from measurements has its own")
    if subject is not None and (shape is not None or measurements is not None):
        raise ValueError("give a subject or shape / measurements, not both: the subject's body has its own")
    named = isinstance(coordinates, Mapping)
    coords = (
        {str(k): np.asarray(v, np.float64) for k, v in coordinates.items()}
        if isinstance(coordinates, Mapping)
        else _rows(coordinates)
    )
    return {
        "shape": _rows(shape),
        "coordinates": coords,
        "named": named,
        "root": _rows(root),
        "skeleton": skeleton,
        "faces": faces,
        "batch": batch,
        "format": fmt,
        "measurements": None if measurements is None else {str(k): float(v) for k, v in measurements.items()},
        "sex": sex,
        "subject": subject_upload(subject),
    }


def _result(_: list[Any], result: R) -> R:
    return result


def _synthesis(doc: Event) -> Synthesis:
    assert isinstance(doc, dict)  # the transports give a synthesis's arrays as a dict
    return Synthesis.from_event(doc)


def _file(doc: Event) -> bytes:
    assert isinstance(doc, dict)  # {"data": the file's bytes}
    return bytes(doc["data"])


def _mesh_fit(_: list[Any], result: w.MeshFit) -> MeshFitResult:
    return MeshFitResult.from_event(result)


_scan_events = reader(w.SCAN_EVENTS, "scan fit event")
_sequence_events = reader(w.SEQUENCE_EVENTS, "sequence fit event")
_upgrade_events = reader(w.UPGRADE_EVENTS, "upgrade event")
_subject_events = reader(SUBJECT_EVENTS, "subject event")


def _subject(_: list[Any], result: SubjectResult) -> SubjectOutput:
    return SubjectOutput.from_event(result)


def model_info() -> Operation[ModelInfo]:
    """DOF names, ranges and units, shape sizes, joint names, asset hashes."""
    return Operation("model_info", read_model_info, _result, idempotent=True)


def synthesize(
    shape: np.ndarray | None = None,
    coordinates: Coordinates = None,
    root: np.ndarray | None = None,
    skeleton: bool = False,
    faces: bool = False,
    batch: int | None = None,
    measurements: Mapping[str, float] | None = None,
    sex: str | None = None,
    subject: SubjectInput | None = None,
) -> Operation[Synthesis]:
    """Posed bodies as arrays. shape (B, n_shape); coordinates (B, n_dof) or {name: value(s)}; root
    (B, 3); see :meth:`synthesize_file` for npz / ply / obj / glb / json bytes.

    Instead of shape, ``measurements`` ({name: value} in metres, kilograms for the mass: ANSUR II names or
    aliases such as stature, mass, waist; any subset, docs/anthropometry.md) build the body, for ``sex``
    (male, female or None); the result's ``built`` holds what was requested and achieved. Or ``subject``
    (a subject file's path or bytes, a ``Subject``, or :meth:`build_subject`'s result): every body is that
    person's."""
    args = synthesis_args(shape, coordinates, root, skeleton, faces, batch, "npz", measurements, sex, subject)
    return Operation("synthesize", _synthesis, _result, args, idempotent=True)


def synthesize_file(
    format: str,
    shape: np.ndarray | None = None,
    coordinates: Coordinates = None,
    root: np.ndarray | None = None,
    skeleton: bool = False,
    measurements: Mapping[str, float] | None = None,
    sex: str | None = None,
    subject: SubjectInput | None = None,
) -> Operation[bytes]:
    """Posed bodies encoded as ``format`` (npz, ply, obj, glb or json; faces included); ``measurements``,
    ``sex`` and ``subject`` as for :meth:`synthesize` (what the build achieved: :meth:`measure` with the
    same ones).

    Raises:
        ValueError: another format, or more than one of shape, measurements and subject (before anything
            is sent)."""
    args = synthesis_args(shape, coordinates, root, skeleton, True, None, format, measurements, sex, subject)
    return Operation("synthesize_file", _file, _result, args, idempotent=True)


_measurements = read_measurements


def measure(
    shape: np.ndarray | None = None,
    coordinates: Coordinates = None,
    measurements: Mapping[str, float] | None = None,
    sex: str | None = None,
    mesh: ScanInput | None = None,
    units: str = "m",
) -> Operation[Measurements]:
    """Anthropometric measurements (docs/anthropometry.md), in metres and kilograms, of one of:

    - bodies given by ``shape`` (B, n_shape), posed by ``coordinates`` ((B, n_dof) or {name: value(s)};
      default the measuring posture);
    - a ``mesh`` in the model's topology (a .npz / .ply path, bytes of an .npz, or a (V, 3) array), in
      ``units`` (m, mm or auto);
    - the body built from ``measurements`` ({name: value}: ANSUR II names or aliases such as stature,
      mass, waist; any subset) for ``sex`` (male, female or None): the answer then holds its ``shape``,
      ``residuals`` and ``unmet`` (``flagged`` when the set cannot all be met).

    Served over REST (``POST /v1/measure``) and gRPC (``Measure``).

    The operation's ``args``: ``mesh`` (file name, bytes) or None, ``units``, ``measurements`` and
    ``sex``, and for shapes the :func:`synthesis_args`.

    Raises:
        ValueError: none or more than one of shape, mesh and measurements (before anything is sent).
    """
    given = [
        k for k, v in (("shape", shape), ("mesh", mesh), ("measurements", measurements)) if v is not None
    ]
    if len(given) != 1:
        raise ValueError(f"give exactly one of shape, mesh and measurements; got {given or 'none'}")
    args: dict[str, Any] = {"mesh": None, "units": units, "measurements": None, "sex": sex}
    if mesh is not None:
        args["mesh"] = scan_upload(mesh, "npz" if isinstance(mesh, bytes | bytearray) else None)
    elif measurements is not None:
        args["measurements"] = {str(k): float(v) for k, v in measurements.items()}
    else:
        args |= synthesis_args(shape, coordinates, None, False, False, None, "npz")
    return Operation("measure", _measurements, _result, args, idempotent=True)


def fit_scan(
    scan: ScanInput,
    format: str | None = None,
    units: str = "auto",
    progress: ProgressCallback | None = None,
    up: str | None = None,
    facing: str | None = None,
    pose: str | None = None,
    sex: str | None = None,
    height_m: float | None = None,
    subject: SubjectInput | None = None,
) -> Operation[MeshFitResult]:
    """Fit a mesh or point cloud: a file (path, or bytes with ``format``) or (N, 3) points; ``units``:
    auto, m or mm; ``progress`` gets each progress event.

    Hints, each optional (the report's ``extra["hints"]`` says how each was used): ``up``, the scan's up
    axis (+x, -x, +y, -y, +z or -z; a bare x is +x) and ``facing``, the axis the person faces (with up: the
    orientation is not searched); ``pose``, the start pose class (standing, sitting, a-pose, t-pose);
    ``sex`` (male, female, neutral; recorded); ``height_m``, the standing height in metres (the fitted
    body's is checked against it).

    ``subject``: a subject file (path, bytes, ``Subject`` or :meth:`build_subject`'s result): the body is
    that person's, their shape and template held fixed; only the orientation, pose and root are fitted.

    Raises:
        ValueError: an axis or pose class that names none of the allowed values (before anything is sent).
    """
    name, data = scan_upload(scan, format)
    args = {
        "name": name,
        "data": data,
        "format": Path(name).suffix.lstrip("."),
        "units": units,
        "hints": scan_hints(up, facing, pose, sex, height_m),
        "subject": subject_upload(subject),
    }
    return Operation("fit_scan", _scan_events, _mesh_fit, args, stream=True, progress=progress)


def scan_hints(
    up: str | None, facing: str | None, pose: str | None, sex: str | None, height_m: float | None
) -> dict[str, str | float]:
    """The hints given, by name (:data:`bodyfit.wire.HINT_NAMES`), axes and pose class in their canonical
    spelling ("z" -> "+z", "A-pose" -> "a-pose"); sex and height are checked by the server.

    Raises:
        ValueError: an axis or pose class that names none of the allowed values.
    """
    values: dict[str, str | float | None] = {
        "up": None if up is None else axis_name(up, "up"),
        "facing": None if facing is None else axis_name(facing, "facing"),
        "pose": None if pose is None else pose_class(pose),
        "sex": sex,
        "height_m": None if height_m is None else float(height_m),
    }
    return {k: v for k, v in values.items() if v is not None}


def fit_sequence(
    frames: np.ndarray,
    weights: np.ndarray | None = None,
    progress: ProgressCallback | None = None,
    chunk: int = 64,
    subject: SubjectInput | None = None,
) -> Operation[SequenceResult]:
    """Fit a registered sequence (T, V, 3) in the model's topology (one shape, per-frame pose);
    ``weights`` (T, V) optional; the server answers in chunks of ``chunk`` frames. ``subject``: a subject
    file (as for :meth:`fit_scan`): no shape fit, every frame is that person's body."""
    f32 = None if weights is None else np.asarray(weights, np.float32)
    args = {
        "frames": np.asarray(frames, np.float32),
        "weights": f32,
        "chunk": chunk,
        "subject": subject_upload(subject),
    }
    return Operation(
        "fit_sequence", _sequence_events, SequenceResult.from_events, args, stream=True, progress=progress
    )


def upgrade(
    sequence: str | os.PathLike[str] | bytes,
    progress: ProgressCallback | None = None,
    chunk: int = 256,
    sex: str | None = None,
    height_m: float | None = None,
    mass_kg: float | None = None,
    up: str | None = None,
    subject: SubjectInput | None = None,
) -> Operation[UpgradeOutput]:
    """Upgrade an AMASS-style .npz (path or bytes) to biomechanical coordinates and OpenSim files.
    ``sex``, ``height_m`` and ``mass_kg`` shape the body when the server has no SMPL-family model file
    (path b). ``up``: the input's up axis (+x, -x, +y, -y, +z or -z; a bare axis is +); None or "auto":
    the server detects it from the motion (AMASS's Z-up needs nothing); the result is Y-up. ``subject``: a
    subject file (as for :meth:`fit_scan`): the body is that person's, only the poses are fitted, and the
    .osim carries their bone scales; not with the shape hints.

    Raises:
        ValueError: ``up`` naming no axis, or a subject with shape hints (before anything is sent).
    """
    name, data = upgrade_upload(sequence)
    axis = None if up is None or up.strip().lower() in ("", "auto") else axis_name(up)
    given = (("sex", sex), ("height_m", height_m), ("mass_kg", mass_kg), ("up", axis))
    hints = {k: v for k, v in given if v is not None}
    if subject is not None and hints.keys() - {"up"}:
        raise ValueError(
            "give a subject or shape hints (sex, height_m, mass_kg), not both: the subject's body has its "
            "own shape"
        )
    args = {"name": name, "data": data, "chunk": chunk, "hints": hints, "subject": subject_upload(subject)}
    return Operation(
        "upgrade", _upgrade_events, UpgradeOutput.from_events, args, stream=True, progress=progress
    )


def upgrade_upload(sequence: SequenceInput) -> tuple[str, bytes]:
    """(file name, bytes) of an AMASS-style .npz given as a path or bytes."""
    if isinstance(sequence, bytes | bytearray):
        return "sequence.npz", bytes(sequence)
    path = Path(sequence)
    return path.name, path.read_bytes()


def frames_npz(frames: np.ndarray, weights: np.ndarray | None) -> bytes:
    """An .npz of ``frames`` (and ``weights``) as float32, the upload of a sequence fit over HTTP."""
    buf = io.BytesIO()
    arrays = {"frames": np.asarray(frames, np.float32)}
    if weights is not None:
        arrays["weights"] = np.asarray(weights, np.float32)
    np.savez(buf, allow_pickle=False, **arrays)
    return buf.getvalue()


def build_subject(
    scans: Sequence[ScanInput],
    units: str = "auto",
    progress: ProgressCallback | None = None,
    up: str | None = None,
    facing: str | None = None,
    pose: str | None = None,
    allow_undetermined: bool = False,
) -> Operation[SubjectOutput]:
    """One person's rig from three or more scans of them in different poses (paths, or (N, 3) point
    arrays; any topology): the subject file and each scan's error under the generic model and the rig.
    ``up``, ``facing`` and ``pose`` go with every raw scan's fit (see :meth:`fit_scan`);
    ``allow_undetermined``: build even when the poses leave limb joints undetermined.

    Raises:
        ValueError: a hint naming none of the allowed values (before anything is sent).
    """
    uploads = [scan_upload(scan, None) for scan in scans]
    # arrays of points are all sent as scan.npz: number them so that the report tells them apart
    names = [f"scan{k}.npz" if name == "scan.npz" else name for k, (name, _) in enumerate(uploads)]
    given = {"up": up and axis_name(up, "up"), "facing": facing and axis_name(facing, "facing")}
    fields = {k: v for k, v in given.items() if v} | ({"pose": pose_class(pose)} if pose else {})
    args = {
        "files": [(n, data) for n, (_, data) in zip(names, uploads, strict=True)],
        "fields": {"units": units, "allow_undetermined": str(allow_undetermined).lower(), **fields},
    }
    return Operation("build_subject", _subject_events, _subject, args, stream=True, progress=progress)

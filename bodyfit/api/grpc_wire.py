"""The gRPC wire: arrays (``bodyfit.v1.Array``: dtype, shape, little-endian C-order bytes), shared by the
server and the gRPC client, and the server's messages built from the documents of :mod:`bodyfit.wire`, so
that REST and gRPC answer the same content."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from bodyfit import wire as w
from bodyfit.api import bodyfit_pb2 as pb
from bodyfit.wire.arrays import MAX_NDIM
from bodyfit.wire.measure import Measurements
from bodyfit.wire.subjects import SubjectResult

DTYPES = w.DTYPES
FLOATS = ("float32", "float64")
"""The dtypes of real-valued inputs (parameters, frames): the server refuses int and bool arrays for them,
as the service core does for every transport."""
MAX_DIMENSION = (1 << 31) - 1
"""Largest declared dimension: no gRPC message holds more elements (an empty array may declare any size,
so a size is checked against this as well as against the data's length)."""


class WireError(ValueError):
    """A malformed array; ``field`` names it."""

    def __init__(self, field: str, detail: str) -> None:
        super().__init__(f"{field}: {detail}")
        self.field = field
        self.detail = detail


def to_proto(a: np.ndarray) -> pb.Array:
    """A numpy array as ``Array`` (float16 / uint types are widened to a wire dtype)."""
    return array_message(w.WireArray.from_numpy(a))


def from_proto(msg: pb.Array, field: str, dtypes: Sequence[str] = DTYPES) -> np.ndarray:
    """The numpy array of ``msg`` (native byte order, a copy); ``dtypes``: those accepted for this field
    (:data:`FLOATS` for real values).

    Raises:
        WireError: a dtype not in ``dtypes``, more than :data:`MAX_NDIM` dimensions, negative sizes or sizes
        above :data:`MAX_DIMENSION`, or a byte count that does not match dtype and shape (all checked before
        any array is built).
    """
    if msg.dtype not in DTYPES:
        raise WireError(field, f"dtype {msg.dtype!r} is not one of {', '.join(DTYPES)}")
    if msg.dtype not in dtypes:
        what = "floats" if tuple(dtypes) == FLOATS else "one of " + ", ".join(dtypes)
        raise WireError(field, f"must hold {what} ({', '.join(dtypes)}); got {msg.dtype}")
    shape = tuple(int(n) for n in msg.shape)
    if len(shape) > MAX_NDIM:
        raise WireError(field, f"shape {shape} has {len(shape)} dimensions; at most {MAX_NDIM} are accepted")
    if any(n < 0 for n in shape):
        raise WireError(field, f"shape {shape} has negative sizes")
    if any(n > MAX_DIMENSION for n in shape):
        raise WireError(
            field, f"shape {shape} declares a size above {MAX_DIMENSION:,}; no message holds that many values"
        )
    dtype = np.dtype(msg.dtype).newbyteorder("<")
    expected = math.prod(shape) * dtype.itemsize  # Python integers: no overflow
    if len(msg.data) != expected:
        raise WireError(
            field, f"holds {len(msg.data)} bytes but dtype {msg.dtype} and shape {shape} need {expected}"
        )
    return np.frombuffer(msg.data, dtype=dtype).reshape(shape).astype(dtype.newbyteorder("="))


def optional(parent: Any, field: str, dtypes: Sequence[str] = DTYPES) -> np.ndarray | None:
    """The array in message field ``field`` of ``parent`` (:func:`from_proto`), or None when the field was
    not set."""
    return from_proto(getattr(parent, field), field, dtypes) if parent.HasField(field) else None


# -- the server's messages from the wire documents -------------------------------------------------------


def array_message(a: w.WireArray) -> pb.Array:
    """A wire array as ``Array`` (the same dtype, shape and bytes)."""
    return pb.Array(dtype=a.dtype, shape=list(a.shape), data=a.data)


def array_fields(arrays: w.WireModel) -> dict[str, pb.Array]:
    """The arrays of a document's ``arrays`` as message fields of the same names."""
    return {name: array_message(a) for name, a in arrays if isinstance(a, w.WireArray)}


def json_text(doc: w.WireModel) -> str:
    """A document as the JSON text of a ``*_json`` field (NaN and infinities as null)."""
    return doc.model_dump_json()


def progress_message(p: w.Progress) -> pb.Progress:
    return pb.Progress(stage=p.stage, done=p.done, total=p.total, message=p.message)


def model_message(info: w.ModelInfo) -> pb.ModelInfo:
    return pb.ModelInfo(
        version=info.version,
        dofs=[pb.Dof(name=d.name, min=d.min, max=d.max, unit=d.unit) for d in info.dofs],
        n_bone=info.n_bone,
        n_identity=info.n_identity,
        n_vertices=info.n_vertices,
        n_faces=info.n_faces,
        joint_names=list(info.joint_names),
        asset_format=info.assets["format"],
        asset_sources=info.assets["sources"],
        asset_sha256=info.assets["sha256"],
    )


def mesh_fit_message(e: w.MeshFit) -> pb.MeshFitResult:
    return pb.MeshFitResult(
        fitted_as=e.fitted_as,
        dof_names=e.dof_names,
        joint_names=e.joint_names,
        report_json=json_text(e.report),
        **array_fields(e.arrays),
    )


def sequence_event(e: w.SequenceChunkEvent | w.SequenceResultEvent) -> pb.FitSequenceEvent:
    """A chunk or the result of a sequence fit as the stream's message."""
    if isinstance(e, w.SequenceChunkEvent):
        chunk = pb.SequenceChunk(start=e.start, stop=e.stop, **array_fields(e.arrays))
        return pb.FitSequenceEvent(chunk=chunk)
    summary = pb.SequenceSummary(
        dof_names=e.dof_names,
        joint_names=e.joint_names,
        stats_json=json_text(e.stats),
        limit_violations=e.limit_violations,
        confident_frames=e.confident_frames,
        **array_fields(e.arrays),
    )
    return pb.FitSequenceEvent(result=summary)


def upgrade_event(e: w.UpgradeChunkEvent | w.UpgradeResultEvent) -> pb.UpgradeEvent:
    """A chunk or the result of an upgrade as the stream's message."""
    if isinstance(e, w.UpgradeChunkEvent):
        return pb.UpgradeEvent(chunk=pb.UpgradeChunk(start=e.start, stop=e.stop, **array_fields(e.arrays)))
    summary = pb.UpgradeSummary(
        dof_names=e.dof_names,
        joint_names=e.joint_names,
        segment_names=e.segment_names,
        summary_json=json_text(e.summary),
        files=e.files,
        **array_fields(e.arrays),
    )
    return pb.UpgradeEvent(result=summary)


def subject_message(e: SubjectResult) -> pb.BuildSubjectEvent:
    """The result of a rig build as the stream's message."""
    result = pb.SubjectResult(
        scans=e.scans,
        generic_mm=e.generic_mm,
        personal_mm=e.personal_mm,
        undetermined_joints=e.undetermined_joints,
        seconds=e.seconds,
        subject=e.subject,
    )
    return pb.BuildSubjectEvent(result=result)


def measure_message(m: Measurements) -> pb.MeasureResponse:
    """A :class:`~bodyfit.wire.measure.Measurements` document as ``MeasureResponse``."""
    out = pb.MeasureResponse(
        measurements=[pb.MeasurementInfo(name=i.name, kind=i.kind, unit=i.unit) for i in m.measurements],
        requested=m.requested or {},
        residuals=m.residuals or {},
        unmet=m.unmet,
        flagged=m.flagged,
    )
    for name, values in m.values.items():
        out.values[name].values.extend(values)
    if m.shape is not None:
        out.shape.CopyFrom(to_proto(np.asarray(m.shape, np.float64)))
    return out


def measure_doc(msg: pb.MeasureResponse) -> dict[str, Any]:
    """``MeasureResponse`` as the document of ``POST /v1/measure`` (a built body is the one with a shape:
    its requested values and residuals; a measured one has neither).

    Raises:
        WireError: a malformed shape array.
    """
    built = msg.HasField("shape")
    return {
        "measurements": [{"name": i.name, "kind": i.kind, "unit": i.unit} for i in msg.measurements],
        "values": {k: list(v.values) for k, v in msg.values.items()},
        "shape": from_proto(msg.shape, "shape", FLOATS).tolist() if built else None,
        "requested": dict(msg.requested) if built else None,
        "residuals": dict(msg.residuals) if built else None,
        "unmet": list(msg.unmet),
        "flagged": msg.flagged,
    }

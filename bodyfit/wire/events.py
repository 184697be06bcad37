"""The events of long work (fits and upgrades) and the answers built from them.

A streamed answer (REST NDJSON with ``Accept: application/x-ndjson``, gRPC server streaming) is a sequence
of events told apart by ``event``: ``progress`` while the work runs, then ``chunk`` events (sequences and
upgrades: frames ``[start, stop)``), then one ``result``; or an ``error`` event (a problem document) when
the work fails midway. One :class:`~pydantic.TypeAdapter` per operation reads them
(:data:`SCAN_EVENTS`, :data:`SEQUENCE_EVENTS`, :data:`UPGRADE_EVENTS`). Without streaming, REST answers one
JSON document: the result without ``event``, plus ``chunks`` (the chunk events without ``event``) for
sequences and upgrades (:class:`MeshFit`, :class:`SequenceAnswer`, :class:`UpgradeAnswer`).

Units: metres for positions, radians for rotational coordinates (metres for translational ones),
millimetres for distances in reports and ``error_mm``.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, TypeAdapter, model_validator

from bodyfit.wire.arrays import Base64Bytes, WireArray
from bodyfit.wire.base import OpenDocument, WireModel

ErrorKind = Literal[
    "invalid_argument",
    "resource_exhausted",
    "unavailable",
    "deadline_exceeded",
    "cancelled",
    "not_found",
    "internal",
]
"""The error kinds shared by REST problem documents and gRPC statuses (trailing ``bodyfit-kind``)."""
GRPC_STATUS_KINDS: dict[str, ErrorKind] = {
    "INVALID_ARGUMENT": "invalid_argument",
    "RESOURCE_EXHAUSTED": "resource_exhausted",
    "UNAVAILABLE": "unavailable",
    "DEADLINE_EXCEEDED": "deadline_exceeded",
    "CANCELLED": "cancelled",
    "UNIMPLEMENTED": "not_found",
    "NOT_FOUND": "not_found",
}
"""gRPC status code name -> the error kind of a status without ``bodyfit-kind`` (the runtime's own)."""
FittedAs = Literal["registered", "SMPL topology", "raw scan"]
"""How a mesh was fitted: our topology vertex to vertex, SMPL's topology through the stored map, or as a
raw scan."""


class _ProgressTag(WireModel):
    event: Literal["progress"] = "progress"


class _ChunkTag(WireModel):
    event: Literal["chunk"] = "chunk"


class _ResultTag(WireModel):
    event: Literal["result"] = "result"


class _ErrorTag(WireModel):
    event: Literal["error"] = "error"


# -- progress and errors -------------------------------------------------------------------------------


class Progress(WireModel):
    """``done`` of ``total`` units of the stage ``stage``, with a human-readable message."""

    stage: str
    done: int
    total: int
    message: str = ""


class ProgressEvent(Progress, _ProgressTag):
    """A :class:`Progress` in a stream."""


class Problem(WireModel):
    """An RFC 7807 problem document (``application/problem+json``): every REST error. ``detail`` says what
    was wrong and how to fix it; ``kind`` is shared with gRPC; ``field`` names the request field at fault,
    when there is one. The server sends every member but ``field`` always; ``type`` and ``title`` may be
    left out, as RFC 7807 allows."""

    type: str = "about:blank"
    title: str | None = None
    status: int = Field(description="the HTTP status")
    detail: str
    kind: ErrorKind
    field: str | None = None


class ErrorEvent(Problem, _ErrorTag):
    """The problem of work that failed after its stream began (the HTTP status was 200 by then)."""


# -- a mesh or scan fit ----------------------------------------------------------------------------------


class DistanceStats(WireModel):
    """Distances in millimetres; null when nothing was measured."""

    mean: float | None
    median: float | None
    p95: float | None
    max: float | None


class FitReport(OpenDocument):
    """What a fit reports about itself: distances of the result to the input (mm), coordinate values
    outside their joint limits, optimiser iterations, wall time (s), whether to trust it and, when not,
    the reasons; ``extra``: numbers particular to the fit (per-stage losses, scan coverage, the hints and how
    each was used under ``hints``, ...).

    Raw scans (and SMPL-topology meshes, refined on their surface) measure both ways: ``distances`` are the
    scan points within ``extra["inlier_threshold_mm"]`` of the fitted surface (``extra["inlier_fraction"]``
    of them); ``scan_to_model`` every scan point, outliers included (its ``max`` is the real maximum);
    ``model_to_scan`` each vertex of the fitted surface to its nearest scan point, weighted by area, over
    the part the scan can show (``extra["model_to_scan_over"]``: the whole body, the side facing a single
    view's sensor, or the head and shoulders), with ``extra["unsupported_fraction"]`` of that area farther
    than ``extra["unsupported_threshold_mm"]`` from every scan point. Null for fits with a correspondence.

    Raw scans also carry a calibrated estimate of the registration's error: ``predicted_error_mm`` (the mean
    distance to the true body the fit is predicted to have) and ``predicted_error_interval_mm`` (its 10% and
    90% quantiles); ``confident`` needs the interval's upper end below the calibrated bound. Null where not
    estimated."""

    distances: DistanceStats
    limit_violations: int
    iterations: int
    seconds: float
    confident: bool
    reasons: tuple[str, ...] = ()
    extra: dict[str, object] = Field(default_factory=dict)
    scan_to_model: DistanceStats | None = None
    model_to_scan: DistanceStats | None = None
    predicted_error_mm: float | None = None
    predicted_error_interval_mm: tuple[float, float] | None = None


class MeshFitArrays(WireModel):
    """shape (n_shape,); coordinates (n_dof,); root (3,) metres; vertices (V, 3), the registration in
    the model's topology; joints (J, 3); to_model (4, 4); all float32.

    The frame convention, the same for every route (registered, SMPL topology, raw scan): ``vertices`` and
    ``joints`` lie in the input's own frame, on the uploaded mesh or scan; ``to_model`` is the rigid map
    from that frame to the one in which shape, coordinates and root pose the model
    (``x_model = to_model @ [x_input, 1]``), the identity when the parameters hold the input's placement
    themselves. Null from a server older than the field."""

    shape: WireArray
    coordinates: WireArray
    root: WireArray
    vertices: WireArray
    joints: WireArray
    to_model: WireArray | None = None


class MeshFit(WireModel):
    """The fit of one mesh or scan (``POST /v1/fit/scan``'s JSON answer); coordinates are named by
    ``dof_names``, joints by ``joint_names``."""

    fitted_as: FittedAs
    dof_names: tuple[str, ...]
    joint_names: tuple[str, ...]
    arrays: MeshFitArrays
    report: FitReport


class MeshFitEvent(MeshFit, _ResultTag):
    """The result event of a scan fit."""


# -- a registered sequence fit ---------------------------------------------------------------------------


class FrameChunk(WireModel):
    """Frames ``[start, stop)`` of a sequence, counted from 0."""

    start: int = Field(ge=0)
    stop: int = Field(ge=0)

    @model_validator(mode="after")
    def _ordered(self) -> FrameChunk:
        if self.stop < self.start:
            raise ValueError(f"stop {self.stop} comes before start {self.start}")
        return self


class SequenceChunkArrays(WireModel):
    """Frames ``[start, stop)``, k of them: coordinates (k, n_dof); root (k, 3); vertices (k, V, 3)
    float32; joints (k, J, 3) float32; error_mm (k,), each frame's mean distance."""

    coordinates: WireArray
    root: WireArray
    vertices: WireArray
    joints: WireArray
    error_mm: WireArray


class SequenceChunk(FrameChunk):
    """The fitted frames ``[start, stop)`` of a sequence."""

    arrays: SequenceChunkArrays


class SequenceChunkEvent(SequenceChunk, _ChunkTag):
    """A chunk event of a sequence fit."""


class SequenceStats(OpenDocument):
    """A sequence fit's numbers: frames, seconds, frames per second, mean distance (mm), the input's and
    the fit's jitter (mm, mean second difference in time) and their ratio, the keyframes the shape was
    fitted on; a jitter that is undefined is null and ``jitter_note`` says why."""

    frames: int
    seconds: float
    fps: float
    mean_mm: float | None
    jitter_input_mm: float | None
    jitter_fit_mm: float | None
    jitter_ratio: float | None
    shape_keyframes: tuple[int, ...]
    jitter_note: str | None = None


class SequenceArrays(WireModel):
    """shape (n_shape,): one shape for every frame."""

    shape: WireArray


class SequenceFit(WireModel):
    """What a sequence fit ends with (the per-frame arrays came in the chunks); ``confident_frames``: how
    many frames' fits are reported confident."""

    dof_names: tuple[str, ...]
    joint_names: tuple[str, ...]
    arrays: SequenceArrays
    stats: SequenceStats
    limit_violations: int
    confident_frames: int | None = None


class SequenceResultEvent(SequenceFit, _ResultTag):
    """The result event of a sequence fit."""


class SequenceAnswer(SequenceFit):
    """``POST /v1/fit/sequence``'s JSON answer: the result and every chunk."""

    chunks: list[SequenceChunk]


# -- an upgrade -------------------------------------------------------------------------------------------


class UpgradeChunkArrays(WireModel):
    """Frames ``[start, stop)``, k of them: coordinates (k, n_dof); root (k, 3); joints (k, J, 3) float32;
    error_mm (k,) (NaN, null in summaries, where there is no input mesh); bad_frames (k,) bool."""

    coordinates: WireArray
    root: WireArray
    joints: WireArray
    error_mm: WireArray
    bad_frames: WireArray


class UpgradeChunk(FrameChunk):
    """The upgraded frames ``[start, stop)``."""

    arrays: UpgradeChunkArrays


class UpgradeChunkEvent(UpgradeChunk, _ChunkTag):
    """A chunk event of an upgrade."""


class UpgradeSummary(OpenDocument):
    """An upgrade's numbers: which path ran ("a": the SMPL-family model file; "b": the joint rotations),
    frames, the bad ones, the input's frame rate, seconds and frames per second, the mean and worst
    per-frame distance to the input meshes (mm; null without input meshes), joint-limit violations, the
    largest frame-to-frame jump (degrees) and notes. Path (b) adds ``proxy_fit_mm``. Both add ``up_axis``
    (the input's up axis), ``up_given``, ``up_weak``, ``floor_found``, ``shape_max_sd`` (largest shape
    coefficient, population SD), ``scale_outliers`` (segments proportioned unlike the population) and
    ``at_limits`` ({coordinate: share of the frames} for coordinates within 1 degree of a joint limit in more
    than 5 % of the frames)."""

    path: Literal["a", "b"]
    frames: int
    bad_frames: tuple[int, ...]
    frame_rate: float
    seconds: float
    fps: float
    v2v_mean_mm: float | None
    v2v_max_frame_mm: float | None
    limit_violations: int
    max_frame_jump_deg: float | None
    notes: tuple[str, ...]


class UpgradeArrays(WireModel):
    """shape (n_shape,); scales (n_segments, 3), each segment's scale factors."""

    shape: WireArray
    scales: WireArray


class UpgradeResult(WireModel):
    """What an upgrade ends with: names, shape and scales, the summary and the files (``npz``, ``json``,
    ``osim``, ``mot``; base64 in JSON, bytes over gRPC). ``segment_names`` names the rows of
    ``arrays.scales``."""

    dof_names: tuple[str, ...]
    joint_names: tuple[str, ...]
    segment_names: tuple[str, ...] = ()
    arrays: UpgradeArrays
    summary: UpgradeSummary
    files: dict[str, Base64Bytes]


class UpgradeResultEvent(UpgradeResult, _ResultTag):
    """The result event of an upgrade."""


class UpgradeAnswer(UpgradeResult):
    """``POST /v1/upgrade``'s JSON answer: the result and every chunk."""

    chunks: list[UpgradeChunk]


# -- the streams ------------------------------------------------------------------------------------------

ScanFitEvent = Annotated[ProgressEvent | MeshFitEvent | ErrorEvent, Field(discriminator="event")]
"""An event of ``POST /v1/fit/scan`` (gRPC ``FitScan``)."""
SequenceFitEvent = Annotated[
    ProgressEvent | SequenceChunkEvent | SequenceResultEvent | ErrorEvent, Field(discriminator="event")
]
"""An event of ``POST /v1/fit/sequence`` (gRPC ``FitSequence``)."""
UpgradeEvent = Annotated[
    ProgressEvent | UpgradeChunkEvent | UpgradeResultEvent | ErrorEvent, Field(discriminator="event")
]
"""An event of ``POST /v1/upgrade`` (gRPC ``Upgrade``)."""

SCAN_EVENTS: TypeAdapter[ProgressEvent | MeshFitEvent | ErrorEvent] = TypeAdapter(ScanFitEvent)
SEQUENCE_EVENTS: TypeAdapter[ProgressEvent | SequenceChunkEvent | SequenceResultEvent | ErrorEvent] = (
    TypeAdapter(SequenceFitEvent)
)
UPGRADE_EVENTS: TypeAdapter[ProgressEvent | UpgradeChunkEvent | UpgradeResultEvent | ErrorEvent] = (
    TypeAdapter(UpgradeEvent)
)

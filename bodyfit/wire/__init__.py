"""The wire contract: pydantic models of every document the REST API answers and every event it streams,
shared by the server (which builds its answers from them and declares them in its OpenAPI document) and
the SDK (which reads the server's answers with them). numpy and pydantic only, so the client install
stays light.

- :mod:`.arrays`: :class:`WireArray`, the array encoding (dtype, shape, base64 little-endian bytes);
- :mod:`.model`: :class:`ModelInfo` (``GET /v1/model``);
- :mod:`.events`: progress, chunk, result and error events of fits and upgrades, their per-operation
  discriminated unions and the JSON answers built from them;
- :mod:`.documents`: health, readiness, a synthesis as JSON;
- :mod:`.hints`: a scan fit's hints (up and facing axes, pose class, sex, height) and their allowed values.

The gRPC wire carries the same content in the messages of ``bodyfit/api/bodyfit.proto``; the gRPC client
turns them into these models, so both transports are read by one set of validators.
"""

from bodyfit.wire.arrays import DTYPES, Base64Bytes, WireArray
from bodyfit.wire.base import OpenDocument, WireModel
from bodyfit.wire.documents import Health, Ready, SynthesisJSON
from bodyfit.wire.events import (
    GRPC_STATUS_KINDS,
    SCAN_EVENTS,
    SEQUENCE_EVENTS,
    UPGRADE_EVENTS,
    DistanceStats,
    ErrorEvent,
    ErrorKind,
    FitReport,
    FittedAs,
    FrameChunk,
    MeshFit,
    MeshFitArrays,
    MeshFitEvent,
    Problem,
    Progress,
    ProgressEvent,
    ScanFitEvent,
    SequenceAnswer,
    SequenceArrays,
    SequenceChunk,
    SequenceChunkArrays,
    SequenceChunkEvent,
    SequenceFit,
    SequenceFitEvent,
    SequenceResultEvent,
    SequenceStats,
    UpgradeAnswer,
    UpgradeArrays,
    UpgradeChunk,
    UpgradeChunkArrays,
    UpgradeChunkEvent,
    UpgradeEvent,
    UpgradeResult,
    UpgradeResultEvent,
    UpgradeSummary,
)
from bodyfit.wire.hints import AXES, HINT_NAMES, POSE_CLASSES, SEXES, Axis, PoseClass, Sex
from bodyfit.wire.model import Assets, Dof, MeshSizes, ModelInfo, ShapeSizes

__all__ = [
    "AXES",
    "DTYPES",
    "GRPC_STATUS_KINDS",
    "HINT_NAMES",
    "POSE_CLASSES",
    "SCAN_EVENTS",
    "SEQUENCE_EVENTS",
    "SEXES",
    "UPGRADE_EVENTS",
    "Assets",
    "Axis",
    "Base64Bytes",
    "DistanceStats",
    "Dof",
    "ErrorEvent",
    "ErrorKind",
    "FitReport",
    "FittedAs",
    "FrameChunk",
    "Health",
    "MeshFit",
    "MeshFitArrays",
    "MeshFitEvent",
    "MeshSizes",
    "ModelInfo",
    "OpenDocument",
    "PoseClass",
    "Problem",
    "Progress",
    "ProgressEvent",
    "Ready",
    "ScanFitEvent",
    "SequenceAnswer",
    "SequenceArrays",
    "SequenceChunk",
    "SequenceChunkArrays",
    "SequenceChunkEvent",
    "SequenceFit",
    "SequenceFitEvent",
    "SequenceResultEvent",
    "SequenceStats",
    "Sex",
    "ShapeSizes",
    "SynthesisJSON",
    "UpgradeAnswer",
    "UpgradeArrays",
    "UpgradeChunk",
    "UpgradeChunkArrays",
    "UpgradeChunkEvent",
    "UpgradeEvent",
    "UpgradeResult",
    "UpgradeResultEvent",
    "UpgradeSummary",
    "WireArray",
    "WireModel",
]

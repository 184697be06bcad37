from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Format(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ARRAYS: _ClassVar[Format]
    NPZ: _ClassVar[Format]
    PLY: _ClassVar[Format]
    OBJ: _ClassVar[Format]
    GLB: _ClassVar[Format]
    JSON: _ClassVar[Format]
ARRAYS: Format
NPZ: Format
PLY: Format
OBJ: Format
GLB: Format
JSON: Format

class Array(_message.Message):
    __slots__ = ("dtype", "shape", "data")
    DTYPE_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    dtype: str
    shape: _containers.RepeatedScalarFieldContainer[int]
    data: bytes
    def __init__(self, dtype: _Optional[str] = ..., shape: _Optional[_Iterable[int]] = ..., data: _Optional[bytes] = ...) -> None: ...

class ModelInfoRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class Dof(_message.Message):
    __slots__ = ("name", "min", "max", "unit")
    NAME_FIELD_NUMBER: _ClassVar[int]
    MIN_FIELD_NUMBER: _ClassVar[int]
    MAX_FIELD_NUMBER: _ClassVar[int]
    UNIT_FIELD_NUMBER: _ClassVar[int]
    name: str
    min: float
    max: float
    unit: str
    def __init__(self, name: _Optional[str] = ..., min: _Optional[float] = ..., max: _Optional[float] = ..., unit: _Optional[str] = ...) -> None: ...

class ModelInfo(_message.Message):
    __slots__ = ("version", "dofs", "n_bone", "n_identity", "n_vertices", "n_faces", "joint_names", "asset_format", "asset_sources", "asset_sha256")
    class AssetSourcesEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: str
        def __init__(self, key: _Optional[str] = ..., value: _Optional[str] = ...) -> None: ...
    class AssetSha256Entry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: str
        def __init__(self, key: _Optional[str] = ..., value: _Optional[str] = ...) -> None: ...
    VERSION_FIELD_NUMBER: _ClassVar[int]
    DOFS_FIELD_NUMBER: _ClassVar[int]
    N_BONE_FIELD_NUMBER: _ClassVar[int]
    N_IDENTITY_FIELD_NUMBER: _ClassVar[int]
    N_VERTICES_FIELD_NUMBER: _ClassVar[int]
    N_FACES_FIELD_NUMBER: _ClassVar[int]
    JOINT_NAMES_FIELD_NUMBER: _ClassVar[int]
    ASSET_FORMAT_FIELD_NUMBER: _ClassVar[int]
    ASSET_SOURCES_FIELD_NUMBER: _ClassVar[int]
    ASSET_SHA256_FIELD_NUMBER: _ClassVar[int]
    version: str
    dofs: _containers.RepeatedCompositeFieldContainer[Dof]
    n_bone: int
    n_identity: int
    n_vertices: int
    n_faces: int
    joint_names: _containers.RepeatedScalarFieldContainer[str]
    asset_format: str
    asset_sources: _containers.ScalarMap[str, str]
    asset_sha256: _containers.ScalarMap[str, str]
    def __init__(self, version: _Optional[str] = ..., dofs: _Optional[_Iterable[_Union[Dof, _Mapping]]] = ..., n_bone: _Optional[int] = ..., n_identity: _Optional[int] = ..., n_vertices: _Optional[int] = ..., n_faces: _Optional[int] = ..., joint_names: _Optional[_Iterable[str]] = ..., asset_format: _Optional[str] = ..., asset_sources: _Optional[_Mapping[str, str]] = ..., asset_sha256: _Optional[_Mapping[str, str]] = ...) -> None: ...

class Values(_message.Message):
    __slots__ = ("values",)
    VALUES_FIELD_NUMBER: _ClassVar[int]
    values: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, values: _Optional[_Iterable[float]] = ...) -> None: ...

class SynthesizeRequest(_message.Message):
    __slots__ = ("shape", "coordinates", "named_coordinates", "root", "skeleton", "format", "faces", "batch", "measurements", "sex", "subject")
    class NamedCoordinatesEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: Values
        def __init__(self, key: _Optional[str] = ..., value: _Optional[_Union[Values, _Mapping]] = ...) -> None: ...
    class MeasurementsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    COORDINATES_FIELD_NUMBER: _ClassVar[int]
    NAMED_COORDINATES_FIELD_NUMBER: _ClassVar[int]
    ROOT_FIELD_NUMBER: _ClassVar[int]
    SKELETON_FIELD_NUMBER: _ClassVar[int]
    FORMAT_FIELD_NUMBER: _ClassVar[int]
    FACES_FIELD_NUMBER: _ClassVar[int]
    BATCH_FIELD_NUMBER: _ClassVar[int]
    MEASUREMENTS_FIELD_NUMBER: _ClassVar[int]
    SEX_FIELD_NUMBER: _ClassVar[int]
    SUBJECT_FIELD_NUMBER: _ClassVar[int]
    shape: Array
    coordinates: Array
    named_coordinates: _containers.MessageMap[str, Values]
    root: Array
    skeleton: bool
    format: Format
    faces: bool
    batch: int
    measurements: _containers.ScalarMap[str, float]
    sex: str
    subject: bytes
    def __init__(self, shape: _Optional[_Union[Array, _Mapping]] = ..., coordinates: _Optional[_Union[Array, _Mapping]] = ..., named_coordinates: _Optional[_Mapping[str, Values]] = ..., root: _Optional[_Union[Array, _Mapping]] = ..., skeleton: _Optional[bool] = ..., format: _Optional[_Union[Format, str]] = ..., faces: _Optional[bool] = ..., batch: _Optional[int] = ..., measurements: _Optional[_Mapping[str, float]] = ..., sex: _Optional[str] = ..., subject: _Optional[bytes] = ...) -> None: ...

class SynthesizeResponse(_message.Message):
    __slots__ = ("data", "media_type", "vertices", "joints", "joint_names", "faces", "bones", "bone_faces", "built")
    DATA_FIELD_NUMBER: _ClassVar[int]
    MEDIA_TYPE_FIELD_NUMBER: _ClassVar[int]
    VERTICES_FIELD_NUMBER: _ClassVar[int]
    JOINTS_FIELD_NUMBER: _ClassVar[int]
    JOINT_NAMES_FIELD_NUMBER: _ClassVar[int]
    FACES_FIELD_NUMBER: _ClassVar[int]
    BONES_FIELD_NUMBER: _ClassVar[int]
    BONE_FACES_FIELD_NUMBER: _ClassVar[int]
    BUILT_FIELD_NUMBER: _ClassVar[int]
    data: bytes
    media_type: str
    vertices: Array
    joints: Array
    joint_names: _containers.RepeatedScalarFieldContainer[str]
    faces: Array
    bones: Array
    bone_faces: Array
    built: MeasureResponse
    def __init__(self, data: _Optional[bytes] = ..., media_type: _Optional[str] = ..., vertices: _Optional[_Union[Array, _Mapping]] = ..., joints: _Optional[_Union[Array, _Mapping]] = ..., joint_names: _Optional[_Iterable[str]] = ..., faces: _Optional[_Union[Array, _Mapping]] = ..., bones: _Optional[_Union[Array, _Mapping]] = ..., bone_faces: _Optional[_Union[Array, _Mapping]] = ..., built: _Optional[_Union[MeasureResponse, _Mapping]] = ...) -> None: ...

class Progress(_message.Message):
    __slots__ = ("stage", "done", "total", "message")
    STAGE_FIELD_NUMBER: _ClassVar[int]
    DONE_FIELD_NUMBER: _ClassVar[int]
    TOTAL_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    stage: str
    done: int
    total: int
    message: str
    def __init__(self, stage: _Optional[str] = ..., done: _Optional[int] = ..., total: _Optional[int] = ..., message: _Optional[str] = ...) -> None: ...

class FitScanRequest(_message.Message):
    __slots__ = ("data", "format", "units", "up", "facing", "pose", "sex", "height_m", "subject")
    DATA_FIELD_NUMBER: _ClassVar[int]
    FORMAT_FIELD_NUMBER: _ClassVar[int]
    UNITS_FIELD_NUMBER: _ClassVar[int]
    UP_FIELD_NUMBER: _ClassVar[int]
    FACING_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    SEX_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_M_FIELD_NUMBER: _ClassVar[int]
    SUBJECT_FIELD_NUMBER: _ClassVar[int]
    data: bytes
    format: str
    units: str
    up: str
    facing: str
    pose: str
    sex: str
    height_m: float
    subject: bytes
    def __init__(self, data: _Optional[bytes] = ..., format: _Optional[str] = ..., units: _Optional[str] = ..., up: _Optional[str] = ..., facing: _Optional[str] = ..., pose: _Optional[str] = ..., sex: _Optional[str] = ..., height_m: _Optional[float] = ..., subject: _Optional[bytes] = ...) -> None: ...

class MeshFitResult(_message.Message):
    __slots__ = ("fitted_as", "shape", "coordinates", "root", "vertices", "joints", "dof_names", "joint_names", "report_json", "to_model")
    FITTED_AS_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    COORDINATES_FIELD_NUMBER: _ClassVar[int]
    ROOT_FIELD_NUMBER: _ClassVar[int]
    VERTICES_FIELD_NUMBER: _ClassVar[int]
    JOINTS_FIELD_NUMBER: _ClassVar[int]
    DOF_NAMES_FIELD_NUMBER: _ClassVar[int]
    JOINT_NAMES_FIELD_NUMBER: _ClassVar[int]
    REPORT_JSON_FIELD_NUMBER: _ClassVar[int]
    TO_MODEL_FIELD_NUMBER: _ClassVar[int]
    fitted_as: str
    shape: Array
    coordinates: Array
    root: Array
    vertices: Array
    joints: Array
    dof_names: _containers.RepeatedScalarFieldContainer[str]
    joint_names: _containers.RepeatedScalarFieldContainer[str]
    report_json: str
    to_model: Array
    def __init__(self, fitted_as: _Optional[str] = ..., shape: _Optional[_Union[Array, _Mapping]] = ..., coordinates: _Optional[_Union[Array, _Mapping]] = ..., root: _Optional[_Union[Array, _Mapping]] = ..., vertices: _Optional[_Union[Array, _Mapping]] = ..., joints: _Optional[_Union[Array, _Mapping]] = ..., dof_names: _Optional[_Iterable[str]] = ..., joint_names: _Optional[_Iterable[str]] = ..., report_json: _Optional[str] = ..., to_model: _Optional[_Union[Array, _Mapping]] = ...) -> None: ...

class FitScanEvent(_message.Message):
    __slots__ = ("progress", "result")
    PROGRESS_FIELD_NUMBER: _ClassVar[int]
    RESULT_FIELD_NUMBER: _ClassVar[int]
    progress: Progress
    result: MeshFitResult
    def __init__(self, progress: _Optional[_Union[Progress, _Mapping]] = ..., result: _Optional[_Union[MeshFitResult, _Mapping]] = ...) -> None: ...

class FitSequenceRequest(_message.Message):
    __slots__ = ("frames", "weights", "chunk", "subject")
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    WEIGHTS_FIELD_NUMBER: _ClassVar[int]
    CHUNK_FIELD_NUMBER: _ClassVar[int]
    SUBJECT_FIELD_NUMBER: _ClassVar[int]
    frames: Array
    weights: Array
    chunk: int
    subject: bytes
    def __init__(self, frames: _Optional[_Union[Array, _Mapping]] = ..., weights: _Optional[_Union[Array, _Mapping]] = ..., chunk: _Optional[int] = ..., subject: _Optional[bytes] = ...) -> None: ...

class SequenceChunk(_message.Message):
    __slots__ = ("start", "stop", "coordinates", "root", "vertices", "joints", "error_mm")
    START_FIELD_NUMBER: _ClassVar[int]
    STOP_FIELD_NUMBER: _ClassVar[int]
    COORDINATES_FIELD_NUMBER: _ClassVar[int]
    ROOT_FIELD_NUMBER: _ClassVar[int]
    VERTICES_FIELD_NUMBER: _ClassVar[int]
    JOINTS_FIELD_NUMBER: _ClassVar[int]
    ERROR_MM_FIELD_NUMBER: _ClassVar[int]
    start: int
    stop: int
    coordinates: Array
    root: Array
    vertices: Array
    joints: Array
    error_mm: Array
    def __init__(self, start: _Optional[int] = ..., stop: _Optional[int] = ..., coordinates: _Optional[_Union[Array, _Mapping]] = ..., root: _Optional[_Union[Array, _Mapping]] = ..., vertices: _Optional[_Union[Array, _Mapping]] = ..., joints: _Optional[_Union[Array, _Mapping]] = ..., error_mm: _Optional[_Union[Array, _Mapping]] = ...) -> None: ...

class SequenceSummary(_message.Message):
    __slots__ = ("shape", "dof_names", "joint_names", "stats_json", "limit_violations", "confident_frames")
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    DOF_NAMES_FIELD_NUMBER: _ClassVar[int]
    JOINT_NAMES_FIELD_NUMBER: _ClassVar[int]
    STATS_JSON_FIELD_NUMBER: _ClassVar[int]
    LIMIT_VIOLATIONS_FIELD_NUMBER: _ClassVar[int]
    CONFIDENT_FRAMES_FIELD_NUMBER: _ClassVar[int]
    shape: Array
    dof_names: _containers.RepeatedScalarFieldContainer[str]
    joint_names: _containers.RepeatedScalarFieldContainer[str]
    stats_json: str
    limit_violations: int
    confident_frames: int
    def __init__(self, shape: _Optional[_Union[Array, _Mapping]] = ..., dof_names: _Optional[_Iterable[str]] = ..., joint_names: _Optional[_Iterable[str]] = ..., stats_json: _Optional[str] = ..., limit_violations: _Optional[int] = ..., confident_frames: _Optional[int] = ...) -> None: ...

class FitSequenceEvent(_message.Message):
    __slots__ = ("progress", "chunk", "result")
    PROGRESS_FIELD_NUMBER: _ClassVar[int]
    CHUNK_FIELD_NUMBER: _ClassVar[int]
    RESULT_FIELD_NUMBER: _ClassVar[int]
    progress: Progress
    chunk: SequenceChunk
    result: SequenceSummary
    def __init__(self, progress: _Optional[_Union[Progress, _Mapping]] = ..., chunk: _Optional[_Union[SequenceChunk, _Mapping]] = ..., result: _Optional[_Union[SequenceSummary, _Mapping]] = ...) -> None: ...

class UpgradeRequest(_message.Message):
    __slots__ = ("data", "filename", "chunk", "sex", "height_m", "mass_kg", "up", "subject")
    DATA_FIELD_NUMBER: _ClassVar[int]
    FILENAME_FIELD_NUMBER: _ClassVar[int]
    CHUNK_FIELD_NUMBER: _ClassVar[int]
    SEX_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_M_FIELD_NUMBER: _ClassVar[int]
    MASS_KG_FIELD_NUMBER: _ClassVar[int]
    UP_FIELD_NUMBER: _ClassVar[int]
    SUBJECT_FIELD_NUMBER: _ClassVar[int]
    data: bytes
    filename: str
    chunk: int
    sex: str
    height_m: float
    mass_kg: float
    up: str
    subject: bytes
    def __init__(self, data: _Optional[bytes] = ..., filename: _Optional[str] = ..., chunk: _Optional[int] = ..., sex: _Optional[str] = ..., height_m: _Optional[float] = ..., mass_kg: _Optional[float] = ..., up: _Optional[str] = ..., subject: _Optional[bytes] = ...) -> None: ...

class UpgradeChunk(_message.Message):
    __slots__ = ("start", "stop", "coordinates", "root", "joints", "error_mm", "bad_frames")
    START_FIELD_NUMBER: _ClassVar[int]
    STOP_FIELD_NUMBER: _ClassVar[int]
    COORDINATES_FIELD_NUMBER: _ClassVar[int]
    ROOT_FIELD_NUMBER: _ClassVar[int]
    JOINTS_FIELD_NUMBER: _ClassVar[int]
    ERROR_MM_FIELD_NUMBER: _ClassVar[int]
    BAD_FRAMES_FIELD_NUMBER: _ClassVar[int]
    start: int
    stop: int
    coordinates: Array
    root: Array
    joints: Array
    error_mm: Array
    bad_frames: Array
    def __init__(self, start: _Optional[int] = ..., stop: _Optional[int] = ..., coordinates: _Optional[_Union[Array, _Mapping]] = ..., root: _Optional[_Union[Array, _Mapping]] = ..., joints: _Optional[_Union[Array, _Mapping]] = ..., error_mm: _Optional[_Union[Array, _Mapping]] = ..., bad_frames: _Optional[_Union[Array, _Mapping]] = ...) -> None: ...

class UpgradeSummary(_message.Message):
    __slots__ = ("dof_names", "joint_names", "shape", "scales", "summary_json", "files", "segment_names")
    class FilesEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: bytes
        def __init__(self, key: _Optional[str] = ..., value: _Optional[bytes] = ...) -> None: ...
    DOF_NAMES_FIELD_NUMBER: _ClassVar[int]
    JOINT_NAMES_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    SCALES_FIELD_NUMBER: _ClassVar[int]
    SUMMARY_JSON_FIELD_NUMBER: _ClassVar[int]
    FILES_FIELD_NUMBER: _ClassVar[int]
    SEGMENT_NAMES_FIELD_NUMBER: _ClassVar[int]
    dof_names: _containers.RepeatedScalarFieldContainer[str]
    joint_names: _containers.RepeatedScalarFieldContainer[str]
    shape: Array
    scales: Array
    summary_json: str
    files: _containers.ScalarMap[str, bytes]
    segment_names: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, dof_names: _Optional[_Iterable[str]] = ..., joint_names: _Optional[_Iterable[str]] = ..., shape: _Optional[_Union[Array, _Mapping]] = ..., scales: _Optional[_Union[Array, _Mapping]] = ..., summary_json: _Optional[str] = ..., files: _Optional[_Mapping[str, bytes]] = ..., segment_names: _Optional[_Iterable[str]] = ...) -> None: ...

class UpgradeEvent(_message.Message):
    __slots__ = ("progress", "chunk", "result")
    PROGRESS_FIELD_NUMBER: _ClassVar[int]
    CHUNK_FIELD_NUMBER: _ClassVar[int]
    RESULT_FIELD_NUMBER: _ClassVar[int]
    progress: Progress
    chunk: UpgradeChunk
    result: UpgradeSummary
    def __init__(self, progress: _Optional[_Union[Progress, _Mapping]] = ..., chunk: _Optional[_Union[UpgradeChunk, _Mapping]] = ..., result: _Optional[_Union[UpgradeSummary, _Mapping]] = ...) -> None: ...

class MeasureRequest(_message.Message):
    __slots__ = ("shape", "coordinates", "named_coordinates", "mesh", "mesh_format", "units", "measurements", "sex")
    class NamedCoordinatesEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: Values
        def __init__(self, key: _Optional[str] = ..., value: _Optional[_Union[Values, _Mapping]] = ...) -> None: ...
    class MeasurementsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    COORDINATES_FIELD_NUMBER: _ClassVar[int]
    NAMED_COORDINATES_FIELD_NUMBER: _ClassVar[int]
    MESH_FIELD_NUMBER: _ClassVar[int]
    MESH_FORMAT_FIELD_NUMBER: _ClassVar[int]
    UNITS_FIELD_NUMBER: _ClassVar[int]
    MEASUREMENTS_FIELD_NUMBER: _ClassVar[int]
    SEX_FIELD_NUMBER: _ClassVar[int]
    shape: Array
    coordinates: Array
    named_coordinates: _containers.MessageMap[str, Values]
    mesh: bytes
    mesh_format: str
    units: str
    measurements: _containers.ScalarMap[str, float]
    sex: str
    def __init__(self, shape: _Optional[_Union[Array, _Mapping]] = ..., coordinates: _Optional[_Union[Array, _Mapping]] = ..., named_coordinates: _Optional[_Mapping[str, Values]] = ..., mesh: _Optional[bytes] = ..., mesh_format: _Optional[str] = ..., units: _Optional[str] = ..., measurements: _Optional[_Mapping[str, float]] = ..., sex: _Optional[str] = ...) -> None: ...

class MeasurementInfo(_message.Message):
    __slots__ = ("name", "kind", "unit")
    NAME_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    UNIT_FIELD_NUMBER: _ClassVar[int]
    name: str
    kind: str
    unit: str
    def __init__(self, name: _Optional[str] = ..., kind: _Optional[str] = ..., unit: _Optional[str] = ...) -> None: ...

class MeasureResponse(_message.Message):
    __slots__ = ("measurements", "values", "shape", "requested", "residuals", "unmet", "flagged")
    class ValuesEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: Values
        def __init__(self, key: _Optional[str] = ..., value: _Optional[_Union[Values, _Mapping]] = ...) -> None: ...
    class RequestedEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    class ResidualsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    MEASUREMENTS_FIELD_NUMBER: _ClassVar[int]
    VALUES_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    REQUESTED_FIELD_NUMBER: _ClassVar[int]
    RESIDUALS_FIELD_NUMBER: _ClassVar[int]
    UNMET_FIELD_NUMBER: _ClassVar[int]
    FLAGGED_FIELD_NUMBER: _ClassVar[int]
    measurements: _containers.RepeatedCompositeFieldContainer[MeasurementInfo]
    values: _containers.MessageMap[str, Values]
    shape: Array
    requested: _containers.ScalarMap[str, float]
    residuals: _containers.ScalarMap[str, float]
    unmet: _containers.RepeatedScalarFieldContainer[str]
    flagged: bool
    def __init__(self, measurements: _Optional[_Iterable[_Union[MeasurementInfo, _Mapping]]] = ..., values: _Optional[_Mapping[str, Values]] = ..., shape: _Optional[_Union[Array, _Mapping]] = ..., requested: _Optional[_Mapping[str, float]] = ..., residuals: _Optional[_Mapping[str, float]] = ..., unmet: _Optional[_Iterable[str]] = ..., flagged: _Optional[bool] = ...) -> None: ...

class ScanFile(_message.Message):
    __slots__ = ("data", "filename", "format")
    DATA_FIELD_NUMBER: _ClassVar[int]
    FILENAME_FIELD_NUMBER: _ClassVar[int]
    FORMAT_FIELD_NUMBER: _ClassVar[int]
    data: bytes
    filename: str
    format: str
    def __init__(self, data: _Optional[bytes] = ..., filename: _Optional[str] = ..., format: _Optional[str] = ...) -> None: ...

class BuildSubjectRequest(_message.Message):
    __slots__ = ("scans", "units", "up", "facing", "pose", "allow_undetermined")
    SCANS_FIELD_NUMBER: _ClassVar[int]
    UNITS_FIELD_NUMBER: _ClassVar[int]
    UP_FIELD_NUMBER: _ClassVar[int]
    FACING_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    ALLOW_UNDETERMINED_FIELD_NUMBER: _ClassVar[int]
    scans: _containers.RepeatedCompositeFieldContainer[ScanFile]
    units: str
    up: str
    facing: str
    pose: str
    allow_undetermined: bool
    def __init__(self, scans: _Optional[_Iterable[_Union[ScanFile, _Mapping]]] = ..., units: _Optional[str] = ..., up: _Optional[str] = ..., facing: _Optional[str] = ..., pose: _Optional[str] = ..., allow_undetermined: _Optional[bool] = ...) -> None: ...

class SubjectResult(_message.Message):
    __slots__ = ("scans", "generic_mm", "personal_mm", "undetermined_joints", "seconds", "subject")
    SCANS_FIELD_NUMBER: _ClassVar[int]
    GENERIC_MM_FIELD_NUMBER: _ClassVar[int]
    PERSONAL_MM_FIELD_NUMBER: _ClassVar[int]
    UNDETERMINED_JOINTS_FIELD_NUMBER: _ClassVar[int]
    SECONDS_FIELD_NUMBER: _ClassVar[int]
    SUBJECT_FIELD_NUMBER: _ClassVar[int]
    scans: _containers.RepeatedScalarFieldContainer[str]
    generic_mm: _containers.RepeatedScalarFieldContainer[float]
    personal_mm: _containers.RepeatedScalarFieldContainer[float]
    undetermined_joints: _containers.RepeatedScalarFieldContainer[str]
    seconds: float
    subject: bytes
    def __init__(self, scans: _Optional[_Iterable[str]] = ..., generic_mm: _Optional[_Iterable[float]] = ..., personal_mm: _Optional[_Iterable[float]] = ..., undetermined_joints: _Optional[_Iterable[str]] = ..., seconds: _Optional[float] = ..., subject: _Optional[bytes] = ...) -> None: ...

class BuildSubjectEvent(_message.Message):
    __slots__ = ("progress", "result")
    PROGRESS_FIELD_NUMBER: _ClassVar[int]
    RESULT_FIELD_NUMBER: _ClassVar[int]
    progress: Progress
    result: SubjectResult
    def __init__(self, progress: _Optional[_Union[Progress, _Mapping]] = ..., result: _Optional[_Union[SubjectResult, _Mapping]] = ...) -> None: ...

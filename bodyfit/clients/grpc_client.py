"""gRPC clients of the bodyfit service: :class:`GrpcClient` (sync) and :class:`AsyncGrpcClient` (grpc.aio).

The same methods and results as the REST clients; numpy in and out over raw little-endian arrays; statuses
become the typed exceptions of :mod:`bodyfit.clients.errors` (the field at fault from the trailing
metadata); default timeouts; idempotent calls (model info, synthesize) retried with backoff on UNAVAILABLE.
Needs the ``grpc`` extra (grpcio, protobuf).
"""

from __future__ import annotations

import asyncio
import json
import os
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import grpc
import numpy as np

from bodyfit.api import bodyfit_pb2 as pb
from bodyfit.api import bodyfit_pb2_grpc as pb_grpc
from bodyfit.api.grpc_wire import STATUS_KINDS, from_proto, to_proto
from bodyfit.clients.errors import ERRORS, BodyfitClientError, ConnectionFailedError, ServerError
from bodyfit.clients.results import (
    MeshFitResult,
    ModelInfo,
    ProgressCallback,
    SequenceResult,
    Synthesis,
    UpgradeOutput,
)
from bodyfit.clients.uploads import ScanInput, scan_upload

DEFAULT_TARGET = "127.0.0.1:50051"
DEFAULT_TIMEOUT = 30.0
FIT_TIMEOUT = 600.0
MAX_MESSAGE = (1 << 31) - 1
FORMATS = {"npz": pb.NPZ, "ply": pb.PLY, "obj": pb.OBJ, "glb": pb.GLB, "json": pb.JSON}
Coordinates = np.ndarray | Mapping[str, float | Sequence[float] | np.ndarray] | None
T = TypeVar("T")


def client_error(exc: grpc.RpcError) -> BodyfitClientError:
    """The typed exception of a failed call (sync ``grpc.Call`` errors and ``grpc.aio.AioRpcError``)."""
    call: Any = exc  # both carry code(), details() and trailing_metadata()
    code = call.code() if callable(getattr(call, "code", None)) else grpc.StatusCode.UNKNOWN
    trailing = (
        dict(call.trailing_metadata() or ()) if callable(getattr(call, "trailing_metadata", None)) else {}
    )
    detail = (call.details() if callable(getattr(call, "details", None)) else None) or str(exc)
    kind = str(trailing.get("bodyfit-kind") or STATUS_KINDS.get(code.name, "internal"))
    field = trailing.get("bodyfit-field")
    if code == grpc.StatusCode.UNAVAILABLE and "bodyfit-kind" not in trailing:
        return ConnectionFailedError(f"cannot reach the bodyfit gRPC server: {detail}", code.name)
    return ERRORS.get(kind, ServerError)(detail, code.name, None if field is None else str(field))


def synth_request(
    shape: np.ndarray | None,
    coordinates: Coordinates,
    root: np.ndarray | None,
    skeleton: bool,
    format: str | None,
    faces: bool,
    batch: int | None,
) -> pb.SynthesizeRequest:
    req = pb.SynthesizeRequest(skeleton=skeleton, faces=faces, batch=batch or 0)
    if format is not None:
        if format not in FORMATS:
            raise ValueError(f"format must be one of {', '.join(FORMATS)}; got {format!r}")
        req.format = FORMATS[format]
    if shape is not None:
        req.shape.CopyFrom(to_proto(np.atleast_2d(np.asarray(shape, np.float64))))
    if isinstance(coordinates, Mapping):
        for name, value in coordinates.items():
            req.named_coordinates[name].values.extend(np.atleast_1d(np.asarray(value, np.float64)).tolist())
    elif coordinates is not None:
        req.coordinates.CopyFrom(to_proto(np.atleast_2d(np.asarray(coordinates, np.float64))))
    if root is not None:
        req.root.CopyFrom(to_proto(np.atleast_2d(np.asarray(root, np.float64))))
    return req


def synthesis(res: pb.SynthesizeResponse) -> Synthesis:
    def opt(name: str) -> np.ndarray | None:
        return from_proto(getattr(res, name), name) if res.HasField(name) else None

    return Synthesis(
        from_proto(res.vertices, "vertices"),
        from_proto(res.joints, "joints"),
        tuple(res.joint_names),
        opt("faces"),
        opt("bones"),
        opt("bone_faces"),
    )


def model_info(res: pb.ModelInfo) -> ModelInfo:
    return ModelInfo(
        dof_names=tuple(d.name for d in res.dofs),
        dof_ranges=np.array([[d.min, d.max] for d in res.dofs], np.float64),
        dof_units=tuple(d.unit for d in res.dofs),
        n_bone=res.n_bone,
        n_identity=res.n_identity,
        n_vertices=res.n_vertices,
        n_faces=res.n_faces,
        joint_names=tuple(res.joint_names),
        assets={
            "format": res.asset_format,
            "sources": dict(res.asset_sources),
            "sha256": dict(res.asset_sha256),
        },
        version=res.version,
    )


def scan_request(scan: ScanInput, format: str | None, units: str) -> pb.FitScanRequest:
    name, data = scan_upload(scan, format)
    return pb.FitScanRequest(data=data, format=Path(name).suffix.lstrip("."), units=units)


def sequence_request(frames: np.ndarray, weights: np.ndarray | None, chunk: int) -> pb.FitSequenceRequest:
    req = pb.FitSequenceRequest(frames=to_proto(np.asarray(frames, np.float32)), chunk=chunk)
    if weights is not None:
        req.weights.CopyFrom(to_proto(np.asarray(weights, np.float32)))
    return req


def upgrade_request(
    sequence: str | os.PathLike[str] | bytes,
    chunk: int,
    sex: str | None = None,
    height_m: float | None = None,
    mass_kg: float | None = None,
) -> pb.UpgradeRequest:
    """The request for an AMASS-style .npz (path or bytes), with path (b)'s shape hints where given."""
    if isinstance(sequence, bytes | bytearray):
        data, name = bytes(sequence), "sequence.npz"
    else:
        path = Path(sequence)
        data, name = path.read_bytes(), path.name
    request = pb.UpgradeRequest(data=data, filename=name, chunk=chunk)
    if sex is not None:
        request.sex = sex
    if height_m is not None:
        request.height_m = height_m
    if mass_kg is not None:
        request.mass_kg = mass_kg
    return request


class _Events:
    """Folds streamed events into a result, forwarding progress."""

    def __init__(self, progress: ProgressCallback | None) -> None:
        self.progress = progress
        self.chunks: list[Any] = []
        self.result: Any = None

    def feed(self, event: Any) -> None:
        kind = event.WhichOneof("event")
        if kind == "progress" and self.progress is not None:
            p = event.progress
            self.progress({"stage": p.stage, "done": p.done, "total": p.total, "message": p.message})
        elif kind == "chunk":
            self.chunks.append(event.chunk)
        elif kind == "result":
            self.result = event.result

    def mesh_fit(self) -> MeshFitResult:
        r = self._final()
        shape, coordinates, root, vertices, joints = (
            from_proto(getattr(r, k), k) for k in ("shape", "coordinates", "root", "vertices", "joints")
        )
        names = tuple(r.dof_names), tuple(r.joint_names)
        return MeshFitResult(
            r.fitted_as, shape, coordinates, root, vertices, joints, *names, json.loads(r.report_json)
        )

    def sequence(self) -> SequenceResult:
        r = self._final()
        chunks = sorted(self.chunks, key=lambda c: c.start)
        arrays = {
            k: np.concatenate([from_proto(getattr(c, k), k) for c in chunks])
            for k in ("coordinates", "root", "vertices", "joints", "error_mm")
        }
        return SequenceResult(
            shape=from_proto(r.shape, "shape"),
            dof_names=tuple(r.dof_names),
            joint_names=tuple(r.joint_names),
            stats=json.loads(r.stats_json),
            limit_violations=int(r.limit_violations),
            **arrays,
        )

    def upgrade(self) -> UpgradeOutput:
        r = self._final()
        chunks = sorted(self.chunks, key=lambda c: c.start)
        arrays = {
            k: np.concatenate([from_proto(getattr(c, k), k) for c in chunks])
            for k in ("coordinates", "root", "joints", "error_mm", "bad_frames")
        }
        return UpgradeOutput(
            shape=from_proto(r.shape, "shape"),
            scales=from_proto(r.scales, "scales"),
            dof_names=tuple(r.dof_names),
            joint_names=tuple(r.joint_names),
            summary=json.loads(r.summary_json),
            files={ext: bytes(data) for ext, data in r.files.items()},
            **arrays,
        )

    def _final(self) -> Any:
        if self.result is None:
            raise ServerError("the server's stream ended without a result")
        return self.result


def _channel_options() -> list[tuple[str, int]]:
    return [("grpc.max_receive_message_length", MAX_MESSAGE), ("grpc.max_send_message_length", MAX_MESSAGE)]


class GrpcClient:
    """Synchronous gRPC client.

    Args:
        target: "host:port" (default 127.0.0.1:50051, or $BODYFIT_GRPC).
        timeout: seconds for unary calls (fits get ``fit_timeout``).
        retries: attempts after the first for idempotent calls when the server is unavailable.
    """

    def __init__(
        self,
        target: str | None = None,
        timeout: float = DEFAULT_TIMEOUT,
        fit_timeout: float = FIT_TIMEOUT,
        retries: int = 3,
    ) -> None:
        self.target = target or os.environ.get("BODYFIT_GRPC", DEFAULT_TARGET)
        self.timeout, self.fit_timeout, self.retries = timeout, fit_timeout, retries
        self._channel = grpc.insecure_channel(self.target, options=_channel_options())
        self._stub = pb_grpc.BodyfitStub(self._channel)

    def __enter__(self) -> GrpcClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._channel.close()

    def _unary(self, call: Callable[..., T], request: Any) -> T:
        for attempt in range(self.retries + 1):
            try:
                return call(request, timeout=self.timeout)
            except grpc.RpcError as exc:
                error = client_error(exc)
            if not error.retryable or attempt == self.retries:
                raise error
            time.sleep(min(0.25 * 2**attempt, 4.0))
        raise AssertionError("unreachable")

    def _stream(self, events: Iterable[Any], fold: _Events) -> _Events:
        try:
            for event in events:
                fold.feed(event)
        except grpc.RpcError as exc:
            raise client_error(exc) from None
        return fold

    def model_info(self) -> ModelInfo:
        return model_info(self._unary(self._stub.GetModelInfo, pb.ModelInfoRequest()))

    def synthesize(
        self,
        shape: np.ndarray | None = None,
        coordinates: Coordinates = None,
        root: np.ndarray | None = None,
        skeleton: bool = False,
        faces: bool = False,
        batch: int | None = None,
    ) -> Synthesis:
        """Posed bodies as arrays (see :meth:`bodyfit.clients.Client.synthesize`)."""
        request = synth_request(shape, coordinates, root, skeleton, None, faces, batch)
        return synthesis(self._unary(self._stub.Synthesize, request))

    def synthesize_file(
        self,
        format: str,
        shape: np.ndarray | None = None,
        coordinates: Coordinates = None,
        root: np.ndarray | None = None,
        skeleton: bool = False,
    ) -> bytes:
        request = synth_request(shape, coordinates, root, skeleton, format, True, None)
        return bytes(self._unary(self._stub.Synthesize, request).data)

    def fit_scan(
        self,
        scan: ScanInput,
        format: str | None = None,
        units: str = "auto",
        progress: ProgressCallback | None = None,
    ) -> MeshFitResult:
        events = self._stub.FitScan(scan_request(scan, format, units), timeout=self.fit_timeout)
        return self._stream(events, _Events(progress)).mesh_fit()

    def fit_sequence(
        self,
        frames: np.ndarray,
        weights: np.ndarray | None = None,
        progress: ProgressCallback | None = None,
        chunk: int = 64,
    ) -> SequenceResult:
        events = self._stub.FitSequence(sequence_request(frames, weights, chunk), timeout=self.fit_timeout)
        return self._stream(events, _Events(progress)).sequence()

    def upgrade(
        self,
        sequence: str | os.PathLike[str] | bytes,
        progress: ProgressCallback | None = None,
        chunk: int = 256,
        sex: str | None = None,
        height_m: float | None = None,
        mass_kg: float | None = None,
    ) -> UpgradeOutput:
        """Upgrade an AMASS-style .npz (path or bytes) to biomechanical coordinates and OpenSim files.
        ``sex``, ``height_m`` and ``mass_kg`` shape the body when the server has no SMPL-family model file
        (path b)."""
        request = upgrade_request(sequence, chunk, sex, height_m, mass_kg)
        events = self._stub.Upgrade(request, timeout=self.fit_timeout)
        return self._stream(events, _Events(progress)).upgrade()


class AsyncGrpcClient:
    """Asynchronous gRPC client (grpc.aio); the same methods as :class:`GrpcClient`, awaited."""

    def __init__(
        self,
        target: str | None = None,
        timeout: float = DEFAULT_TIMEOUT,
        fit_timeout: float = FIT_TIMEOUT,
        retries: int = 3,
    ) -> None:
        self.target = target or os.environ.get("BODYFIT_GRPC", DEFAULT_TARGET)
        self.timeout, self.fit_timeout, self.retries = timeout, fit_timeout, retries
        self._channel = grpc.aio.insecure_channel(self.target, options=_channel_options())
        self._stub = pb_grpc.BodyfitStub(self._channel)

    async def __aenter__(self) -> AsyncGrpcClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def close(self) -> None:
        await self._channel.close()

    async def _unary(self, call: Callable[..., Any], request: Any) -> Any:
        for attempt in range(self.retries + 1):
            try:
                return await call(request, timeout=self.timeout)
            except grpc.RpcError as exc:
                error = client_error(exc)
            if not error.retryable or attempt == self.retries:
                raise error
            await asyncio.sleep(min(0.25 * 2**attempt, 4.0))
        raise AssertionError("unreachable")

    async def _stream(self, call: Any, fold: _Events) -> _Events:
        try:
            async for event in call:
                fold.feed(event)
        except grpc.RpcError as exc:
            raise client_error(exc) from None
        return fold

    async def model_info(self) -> ModelInfo:
        return model_info(await self._unary(self._stub.GetModelInfo, pb.ModelInfoRequest()))

    async def synthesize(
        self,
        shape: np.ndarray | None = None,
        coordinates: Coordinates = None,
        root: np.ndarray | None = None,
        skeleton: bool = False,
        faces: bool = False,
        batch: int | None = None,
    ) -> Synthesis:
        request = synth_request(shape, coordinates, root, skeleton, None, faces, batch)
        return synthesis(await self._unary(self._stub.Synthesize, request))

    async def fit_scan(
        self,
        scan: ScanInput,
        format: str | None = None,
        units: str = "auto",
        progress: ProgressCallback | None = None,
    ) -> MeshFitResult:
        call = self._stub.FitScan(scan_request(scan, format, units), timeout=self.fit_timeout)
        return (await self._stream(call, _Events(progress))).mesh_fit()

    async def fit_sequence(
        self,
        frames: np.ndarray,
        weights: np.ndarray | None = None,
        progress: ProgressCallback | None = None,
        chunk: int = 64,
    ) -> SequenceResult:
        call = self._stub.FitSequence(sequence_request(frames, weights, chunk), timeout=self.fit_timeout)
        return (await self._stream(call, _Events(progress))).sequence()

    async def upgrade(
        self,
        sequence: str | os.PathLike[str] | bytes,
        progress: ProgressCallback | None = None,
        chunk: int = 256,
        sex: str | None = None,
        height_m: float | None = None,
        mass_kg: float | None = None,
    ) -> UpgradeOutput:
        request = upgrade_request(sequence, chunk, sex, height_m, mass_kg)
        call = self._stub.Upgrade(request, timeout=self.fit_timeout)
        return (await self._stream(call, _Events(progress))).upgrade()

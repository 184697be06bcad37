"""The gRPC transport: ``bodyfit.v1.Bodyfit`` over the service core, with health and reflection.

Errors become statuses (INVALID_ARGUMENT, RESOURCE_EXHAUSTED, UNAVAILABLE, DEADLINE_EXCEEDED, CANCELLED;
anything unexpected INTERNAL with a generic message, logged here); the trailing metadata "bodyfit-kind" and
"bodyfit-field" carry the error kind and the field at fault. A request's time limit is the client's
deadline or the server's ``max_seconds``, whichever is shorter; a client that cancels or goes away cancels
its work.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Iterator
from concurrent import futures
from contextlib import contextmanager
from pathlib import Path, PurePath
from typing import Any, TypeVar

import grpc
import numpy as np
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from bodyfit.api import bodyfit_pb2 as pb
from bodyfit.api import bodyfit_pb2_grpc as pb_grpc
from bodyfit.api import results
from bodyfit.api.grpc_wire import (
    FLOATS,
    WireError,
    from_proto,
    measure_message,
    mesh_fit_message,
    model_message,
    optional,
    progress_message,
    sequence_event,
    subject_message,
    to_proto,
    upgrade_event,
)
from bodyfit.api.metrics import Metrics
from bodyfit.api.settings import ServiceSettings
from bodyfit.io.scans import Scan
from bodyfit.models.rig.build import RigConfig
from bodyfit.service.core import BodyService, SynthRequest, shape_hints, upgrade_up
from bodyfit.service.errors import InvalidInputError, ServiceError, as_service_error
from bodyfit.service.formats import MEDIA_TYPES, encode_bodies
from bodyfit.service.hints import ScanHints
from bodyfit.service.jobs import Job, Progress
from bodyfit.service.subjects import build_subject
from bodyfit.wire.hints import HINT_NAMES

LOG = logging.getLogger("bodyfit.grpc")
SERVICE_NAME = pb.DESCRIPTOR.services_by_name["Bodyfit"].full_name
STATUS = {
    "invalid_argument": grpc.StatusCode.INVALID_ARGUMENT,
    "resource_exhausted": grpc.StatusCode.RESOURCE_EXHAUSTED,
    "unavailable": grpc.StatusCode.UNAVAILABLE,
    "deadline_exceeded": grpc.StatusCode.DEADLINE_EXCEEDED,
    "cancelled": grpc.StatusCode.CANCELLED,
}
FORMATS = {pb.NPZ: "npz", pb.PLY: "ply", pb.OBJ: "obj", pb.GLB: "glb", pb.JSON: "json"}
_BUG = "the server failed unexpectedly; the error is logged on the server. Please report it."
T = TypeVar("T")


def message_limit(settings: ServiceSettings) -> int:
    """Largest gRPC message both ways: the upload limit plus room for the envelope (at most 2 GiB)."""
    return min(settings.limits().max_upload_bytes + (1 << 20), (1 << 31) - 1)


def _set(request: Any, name: str) -> Any:
    """The value of an optional field of ``request``, None when it was not set."""
    return getattr(request, name) if request.HasField(name) else None


def _coordinates(request: pb.SynthesizeRequest | pb.MeasureRequest) -> Any:
    """The request's coordinates: the (B, n_dof) array or {DOF name: values}, None when neither is set.

    Raises:
        InvalidInputError: both are set.
    """
    coordinates: Any = optional(request, "coordinates", FLOATS)
    if request.named_coordinates:
        if coordinates is not None:
            raise InvalidInputError("give coordinates or named_coordinates, not both", "coordinates")
        coordinates = {k: np.asarray(v.values) for k, v in request.named_coordinates.items()}
    return coordinates


def _scan_file(service: BodyService, scan: pb.ScanFile, name: str, units: str) -> Scan:
    """One scan of a BuildSubject request, read in its format (the name's suffix when not given).

    Raises:
        InvalidInputError: no format to read it in, or a file that cannot be read.
    """
    fmt = scan.format or PurePath(name).suffix.lstrip(".")
    if not fmt:
        raise InvalidInputError(f"{name!r} has no suffix and no format: give the scan's format", "scans")
    return service.read_scan(scan.data, fmt, units or "auto")


def _progress(p: Progress) -> pb.Progress:
    return progress_message(results.progress_event(p))


class BodyfitServicer(pb_grpc.BodyfitServicer):
    """Translates messages to core calls and core errors to statuses."""

    def __init__(self, service: BodyService, settings: ServiceSettings, metrics: Metrics) -> None:
        self.service = service
        self.settings = settings
        self.metrics = metrics

    # -- unary -----------------------------------------------------------------------------------------
    def GetModelInfo(self, request: pb.ModelInfoRequest, context: grpc.ServicerContext) -> pb.ModelInfo:
        return self._unary("GetModelInfo", context, self._model_info)

    def _model_info(self) -> pb.ModelInfo:
        return model_message(self.service.info())

    def Synthesize(
        self, request: pb.SynthesizeRequest, context: grpc.ServicerContext
    ) -> pb.SynthesizeResponse:
        return self._unary("Synthesize", context, lambda: self._synthesize(request))

    def _synthesize(self, request: pb.SynthesizeRequest) -> pb.SynthesizeResponse:
        if request.format not in (pb.ARRAYS, *FORMATS):
            raise InvalidInputError(f"unknown format {request.format}; use a Format value", "format")
        synth = SynthRequest(
            shape=optional(request, "shape", FLOATS),
            coordinates=_coordinates(request),
            root=optional(request, "root", FLOATS),
            skeleton=request.skeleton,
            batch=request.batch or None,
            measurements=dict(request.measurements) if request.measurements else None,
            sex=_set(request, "sex"),
            subject=request.subject or None,
        )
        synth, built = self.service.with_built_shape(synth)
        out = self._synthesized(request, synth)
        if built is not None:  # as REST's header: kinds and units by name in docs/anthropometry.md
            out.built.CopyFrom(measure_message(built.model_copy(update={"measurements": []})))
        return out

    def _synthesized(self, request: pb.SynthesizeRequest, synth: SynthRequest) -> pb.SynthesizeResponse:
        bodies = self.service.synthesize(synth)
        if request.format != pb.ARRAYS:
            fmt = FORMATS[request.format]
            data = encode_bodies(bodies, fmt, faces=request.faces)
            return pb.SynthesizeResponse(data=data, media_type=MEDIA_TYPES[fmt])
        out = pb.SynthesizeResponse(
            vertices=to_proto(bodies.vertices), joints=to_proto(bodies.joints), joint_names=bodies.joint_names
        )
        if request.faces:
            out.faces.CopyFrom(to_proto(bodies.faces))
        if bodies.bones is not None and bodies.bone_faces is not None:
            out.bones.CopyFrom(to_proto(bodies.bones))
            if request.faces:
                out.bone_faces.CopyFrom(to_proto(bodies.bone_faces))
        return out

    def Measure(self, request: pb.MeasureRequest, context: grpc.ServicerContext) -> pb.MeasureResponse:
        return self._unary("Measure", context, lambda: self._measure(request))

    def _measure(self, request: pb.MeasureRequest) -> pb.MeasureResponse:
        """Exactly one of shape, mesh and measurements, as ``POST /v1/measure``."""
        given = [
            name
            for name, present in (
                ("shape", request.HasField("shape")),
                ("mesh", bool(request.mesh)),
                ("measurements", bool(request.measurements)),
            )
            if present
        ]
        if len(given) != 1:
            raise InvalidInputError(
                f"send exactly one of shape, mesh and measurements; got {', '.join(given) or 'none'}",
                given[-1] if given else "shape",
            )
        service = self.service
        if request.measurements:
            answer = service.measure(measurements=dict(request.measurements), sex=_set(request, "sex"))
        elif request.mesh:
            fmt = request.mesh_format or "npz"
            scan = service.read_scan(request.mesh, fmt, request.units or "m")
            answer = service.measure(vertices=scan.points)
        else:
            synth = SynthRequest(shape=optional(request, "shape", FLOATS), coordinates=_coordinates(request))
            answer = service.measure(synth)
        return measure_message(answer)

    # -- streaming -------------------------------------------------------------------------------------
    def FitScan(self, request: pb.FitScanRequest, context: grpc.ServicerContext) -> Iterator[pb.FitScanEvent]:
        service = self.service
        info = service.info()

        def work(job: Job) -> list[pb.FitScanEvent]:
            hints = ScanHints.given(*(_set(request, name) for name in HINT_NAMES))
            body = service.subject_body(request.subject or None)
            scan = service.read_scan(request.data, request.format or "", request.units or "auto")
            fit = service.fit_mesh(scan, job, hints, body)
            result = results.mesh_fit_result(fit, list(info.dof_names), list(info.joint_names))
            return [pb.FitScanEvent(result=mesh_fit_message(result))]

        return self._stream("FitScan", context, work, lambda p: pb.FitScanEvent(progress=_progress(p)))

    def FitSequence(
        self, request: pb.FitSequenceRequest, context: grpc.ServicerContext
    ) -> Iterator[pb.FitSequenceEvent]:
        service = self.service
        joint_names = list(service.info().joint_names)
        chunk = request.chunk or 64

        def work(job: Job) -> list[pb.FitSequenceEvent]:
            try:
                frames = from_proto(request.frames, "frames", FLOATS)
                weights = optional(request, "weights")
            except WireError as exc:
                raise InvalidInputError(exc.detail, exc.field) from None
            if chunk < 1:
                raise InvalidInputError(f"chunk must be at least 1; got {chunk}", "chunk")
            if frames.ndim >= 1 and len(frames) > service.limits.max_frames:
                service.fit_sequence(frames)  # raises the limit error
            body = service.subject_body(request.subject or None)
            chunks = results.SequenceChunker(chunk, lambda e: job.emit(sequence_event(e)))
            fit = service.fit_sequence(frames, weights, job, on_frames=chunks, body=body)
            chunks.flush()
            return [sequence_event(results.sequence_summary(fit, joint_names))]

        return self._stream(
            "FitSequence", context, work, lambda p: pb.FitSequenceEvent(progress=_progress(p))
        )

    def Upgrade(self, request: pb.UpgradeRequest, context: grpc.ServicerContext) -> Iterator[pb.UpgradeEvent]:
        service = self.service
        chunk = request.chunk or 256
        name = request.filename or "upload.npz"

        def work(job: Job) -> list[pb.UpgradeEvent]:
            if chunk < 1:
                raise InvalidInputError(f"chunk must be at least 1; got {chunk}", "chunk")
            up = upgrade_up(_set(request, "up"))
            hints = shape_hints(*(_set(request, name) for name in ("sex", "height_m", "mass_kg")))
            body = service.subject_body(request.subject or None)
            result = service.upgrade(service.read_upgrade(request.data, name), job, hints, up, body)
            files = service.upgrade_files(result, Path(name).stem or "upgrade")
            chunks = [upgrade_event(e) for e in results.upgrade_chunks(result, chunk)]
            return [*chunks, upgrade_event(results.upgrade_summary(result, files))]

        return self._stream("Upgrade", context, work, lambda p: pb.UpgradeEvent(progress=_progress(p)))

    def BuildSubject(
        self, request: pb.BuildSubjectRequest, context: grpc.ServicerContext
    ) -> Iterator[pb.BuildSubjectEvent]:
        service = self.service

        def work(job: Job) -> list[pb.BuildSubjectEvent]:
            hints = ScanHints.given(*(_set(request, name) for name in ("up", "facing", "pose")))
            names = [f.filename or f"scan{k}" for k, f in enumerate(request.scans)]
            scans = [_scan_file(service, f, name, request.units) for f, name in zip(request.scans, names)]
            config = RigConfig(allow_undetermined=request.allow_undetermined)
            built = build_subject(service, scans, names, job, hints, config)
            return [subject_message(results.subject_result(built))]

        return self._stream(
            "BuildSubject", context, work, lambda p: pb.BuildSubjectEvent(progress=_progress(p))
        )

    # -- plumbing --------------------------------------------------------------------------------------
    @contextmanager
    def _served(self, name: str, context: grpc.ServicerContext) -> Iterator[None]:
        """Metrics around a call, and its errors as statuses (context.abort raises for gRPC)."""
        began = time.perf_counter()
        outcome = "OK"
        self.metrics.in_flight.labels("grpc").inc()
        try:
            try:
                yield
            except WireError as exc:
                raise InvalidInputError(exc.detail, exc.field) from None
        except Exception as exc:
            error = as_service_error(exc)  # the model layer's input errors are the client's too
            if error is None:
                outcome = "INTERNAL"
                LOG.exception("unhandled error in %s", name)
                context.abort(grpc.StatusCode.INTERNAL, _BUG)
            else:
                outcome = STATUS.get(error.kind, grpc.StatusCode.INTERNAL).name
                self._abort(context, error)
        finally:
            m = self.metrics
            m.in_flight.labels("grpc").dec()
            m.latency.labels("grpc", name).observe(time.perf_counter() - began)
            m.requests.labels("grpc", name, outcome).inc()

    def _unary(self, name: str, context: grpc.ServicerContext, call: Callable[[], T]) -> T:
        with self._served(name, context):
            return call()
        raise AssertionError("unreachable")  # _served aborts (raises) on every error

    def _stream(
        self,
        name: str,
        context: grpc.ServicerContext,
        work: Callable[[Job], list[T]],
        progress_event: Callable[[Progress], T],
    ) -> Iterator[T]:
        """Run ``work`` in a thread; yield its progress and the events it emits (already messages) as they
        come, then its result events."""
        remaining = context.time_remaining()
        limit = self.service.limits.max_seconds
        events: queue.SimpleQueue[Progress | T | None] = queue.SimpleQueue()
        timeout = limit if remaining is None else min(limit, remaining)
        job = Job(timeout_s=timeout, on_progress=events.put, on_event=events.put)
        context.add_callback(job.cancel)  # the RPC ended: stop the work if it still runs
        result: list[T] = []
        failure: list[BaseException] = []

        def run() -> None:
            try:
                result.extend(work(job))
            except BaseException as exc:
                failure.append(exc)
            finally:
                events.put(None)

        with self._served(name, context):
            threading.Thread(target=run, name=f"bodyfit-{name}", daemon=True).start()
            try:
                while (p := events.get()) is not None:
                    yield progress_event(p) if isinstance(p, Progress) else p
                if failure:
                    raise failure[0]
                yield from result
            finally:
                job.cancel()

    def _abort(self, context: grpc.ServicerContext, exc: ServiceError) -> None:
        metadata = [("bodyfit-kind", exc.kind)]
        if exc.field is not None:
            metadata.append(("bodyfit-field", exc.field))
        context.set_trailing_metadata(tuple(metadata))
        context.abort(STATUS.get(exc.kind, grpc.StatusCode.INTERNAL), exc.detail)


def create_grpc_server(
    service: BodyService,
    address: str,
    settings: ServiceSettings | None = None,
    metrics: Metrics | None = None,
) -> tuple[grpc.Server, int]:
    """A started-ready (call ``.start()``) gRPC server on ``address`` ("host:port"; port 0 picks one) with
    the Bodyfit service, health (SERVING) and reflection. Returns the server and its bound port."""
    settings = settings or ServiceSettings()
    limit = message_limit(settings)
    server = grpc.server(
        futures.ThreadPoolExecutor(max_workers=32, thread_name_prefix="bodyfit-grpc"),
        options=[("grpc.max_receive_message_length", limit), ("grpc.max_send_message_length", limit)],
    )
    pb_grpc.add_BodyfitServicer_to_server(BodyfitServicer(service, settings, metrics or Metrics()), server)
    health_servicer = health.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    for name in ("", SERVICE_NAME):
        health_servicer.set(name, health_pb2.HealthCheckResponse.SERVING)
    reflection.enable_server_reflection((SERVICE_NAME, health.SERVICE_NAME, reflection.SERVICE_NAME), server)
    port = server.add_insecure_port(address)
    if port == 0:
        raise OSError(f"cannot bind gRPC to {address}")
    return server, port

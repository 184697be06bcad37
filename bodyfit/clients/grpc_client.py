"""gRPC clients of the bodyfit service: :class:`GrpcClient` (sync) and :class:`AsyncGrpcClient` (grpc.aio).

The same methods and results as the REST clients (:mod:`bodyfit.clients.core` declares them once and
reads the answers of both with the models of :mod:`bodyfit.wire`); numpy in and out over raw little-endian
arrays; statuses become the typed exceptions of
:mod:`bodyfit.clients.errors` (the field at fault from the trailing metadata); default timeouts; retries by
:class:`~bodyfit.clients.core.RetryPolicy`. This module only turns an operation into a request message and
the answers into documents of the REST answers' shape. Needs the ``grpc`` extra (grpcio, protobuf).
"""

from __future__ import annotations

import json
import os
from collections.abc import AsyncGenerator, Callable, Generator
from typing import Any, Generic, TypeVar

import grpc
import numpy as np
from google.protobuf.message import Message

from bodyfit.api import bodyfit_pb2 as pb
from bodyfit.api import bodyfit_pb2_grpc as pb_grpc
from bodyfit.api.grpc_wire import measure_doc, to_proto
from bodyfit.clients.core import AsyncClientCore, Event, Operation, SyncClientCore, parse_retry_after
from bodyfit.clients.core import operations as ops
from bodyfit.clients.core.base import async_method, retry_policy, sync_method
from bodyfit.clients.core.operations import Coordinates
from bodyfit.clients.core.retry import DEFAULT_RETRIES, RetryPolicy
from bodyfit.clients.errors import BodyfitClientError, InvalidRequestError, ServerError, error_from_status

DEFAULT_TARGET = "127.0.0.1:50051"
DEFAULT_TIMEOUT = 30.0
FIT_TIMEOUT = 600.0
MAX_MESSAGE = (1 << 31) - 1
FORMATS = {"npz": pb.NPZ, "ply": pb.PLY, "obj": pb.OBJ, "glb": pb.GLB, "json": pb.JSON}
RPCS = {
    "model_info": "GetModelInfo",
    "synthesize": "Synthesize",
    "synthesize_file": "Synthesize",
    "fit_scan": "FitScan",
    "fit_sequence": "FitSequence",
    "upgrade": "Upgrade",
    "measure": "Measure",
    "build_subject": "BuildSubject",
}
C = TypeVar("C", grpc.Channel, grpc.aio.Channel)
__all__ = ["AsyncGrpcClient", "Coordinates", "GrpcClient", "RetryPolicy", "client_error"]


def client_error(exc: grpc.RpcError) -> BodyfitClientError:
    """The typed exception of a failed call (sync ``grpc.Call`` errors and ``grpc.aio.AioRpcError``)."""
    call: Any = exc  # both carry code(), details() and trailing_metadata()
    code = call.code() if callable(getattr(call, "code", None)) else grpc.StatusCode.UNKNOWN
    trailing = (
        dict(call.trailing_metadata() or ()) if callable(getattr(call, "trailing_metadata", None)) else {}
    )
    detail = (call.details() if callable(getattr(call, "details", None)) else None) or str(exc)
    pushback = parse_retry_after(str(trailing.get("grpc-retry-pushback-ms", "")))  # gRPC's retry hint
    retry_after = None if pushback is None else pushback / 1000.0
    return error_from_status(code.name, detail, trailing, retry_after)


def request_of(op: Operation[Any]) -> Message:
    """The request message of an operation."""
    a = op.args
    if op.name == "model_info":
        return pb.ModelInfoRequest()
    if op.name in ("synthesize", "synthesize_file"):
        return synth_request(a, op.name == "synthesize_file")
    if op.name == "measure":
        return measure_request(a)
    subject = a.get("subject") or b""
    if op.name == "fit_scan":
        hints = a["hints"]
        return pb.FitScanRequest(
            data=a["data"], format=a["format"], units=a["units"], subject=subject, **hints
        )
    if op.name == "fit_sequence":
        weights = None if a["weights"] is None else to_proto(a["weights"])
        frames = to_proto(a["frames"])
        return pb.FitSequenceRequest(frames=frames, weights=weights, chunk=a["chunk"], subject=subject)
    if op.name == "build_subject":
        return subject_request(a)
    hints = a["hints"]
    return pb.UpgradeRequest(data=a["data"], filename=a["name"], chunk=a["chunk"], subject=subject, **hints)


def subject_request(a: dict[str, Any]) -> pb.BuildSubjectRequest:
    """The BuildSubject request of a build_subject operation's arguments (files and form fields)."""
    fields = dict(a["fields"])
    allow = fields.pop("allow_undetermined") == "true"
    scans = [pb.ScanFile(data=data, filename=name) for name, data in a["files"]]
    return pb.BuildSubjectRequest(scans=scans, allow_undetermined=allow, **fields)


def synth_request(a: dict[str, Any], file: bool) -> pb.SynthesizeRequest:
    req = pb.SynthesizeRequest(skeleton=a["skeleton"], faces=a["faces"], batch=a["batch"] or 0)
    if file:
        req.format = FORMATS[a["format"]]
    _set_arrays(req, a, ("shape", "coordinates", "root"))
    if a["measurements"] is not None:
        req.measurements.update(a["measurements"])
    if a["sex"] is not None:
        req.sex = a["sex"]
    if a["subject"] is not None:
        req.subject = a["subject"]
    return req


def measure_request(a: dict[str, Any]) -> pb.MeasureRequest:
    """The Measure request of a measure operation's arguments (one of mesh, measurements, shape)."""
    req = pb.MeasureRequest(units=a["units"])
    if a["mesh"] is not None:
        name, data = a["mesh"]
        req.mesh, req.mesh_format = data, os.path.splitext(name)[1].lstrip(".").lower()
    elif a["measurements"] is not None:
        req.measurements.update(a["measurements"])
        if a["sex"] is not None:
            req.sex = a["sex"]
    else:
        _set_arrays(req, a, ("shape", "coordinates"))
    return req


def _set_arrays(
    req: pb.SynthesizeRequest | pb.MeasureRequest, a: dict[str, Any], keys: tuple[str, ...]
) -> None:
    """Copy the arrays of ``a`` that are set into ``req`` (named coordinates into named_coordinates)."""
    for key in keys:
        value = a[key]
        if isinstance(value, dict):
            for name, v in value.items():
                req.named_coordinates[name].values.extend(np.atleast_1d(v).tolist())
        elif value is not None:
            getattr(req, key).CopyFrom(to_proto(value))


def message_doc(msg: Message) -> dict[str, Any]:
    """A message as the REST document of the same content: arrays under "arrays" as
    ``{"dtype", "shape", "data"}`` (raw bytes), ``*_json`` strings parsed (without the suffix), repeated
    fields as lists, maps as dicts.

    Raises:
        ValueError: a ``*_json`` field that is not JSON.
    """
    doc: dict[str, Any] = {}
    arrays = {}
    for f in msg.DESCRIPTOR.fields:
        value = getattr(msg, f.name)
        if f.message_type is pb.Array.DESCRIPTOR:
            if msg.HasField(f.name):
                arrays[f.name] = {"dtype": value.dtype, "shape": list(value.shape), "data": value.data}
        elif f.name.endswith("_json"):
            doc[f.name.removesuffix("_json")] = json.loads(value)
        elif f.message_type is not None and f.message_type.GetOptions().map_entry:
            doc[f.name] = dict(value)
        else:
            doc[f.name] = list(value) if f.is_repeated else value
    if arrays:
        doc["arrays"] = arrays
    return doc


def model_doc(res: pb.ModelInfo) -> dict[str, Any]:
    """GetModelInfo's answer as REST's GET /v1/model document."""
    return {
        "dofs": [{"name": d.name, "min": d.min, "max": d.max, "unit": d.unit} for d in res.dofs],
        "shape": {"n_bone": res.n_bone, "n_identity": res.n_identity, "n_shape": res.n_bone + res.n_identity},
        "mesh": {"n_vertices": res.n_vertices, "n_faces": res.n_faces},
        "joint_names": list(res.joint_names),
        "assets": {
            "format": res.asset_format,
            "sources": dict(res.asset_sources),
            "sha256": dict(res.asset_sha256),
        },
        "version": res.version,
    }


def answer_event(op: Operation[Any], res: Any) -> Event:
    """The document of a unary answer."""
    if op.name == "model_info":
        return model_doc(res)
    if op.name == "measure":
        return measure_doc(res)
    doc = _doc(res)
    if op.name in ("synthesize", "synthesize_file"):
        doc.pop("built", None)
        if res.HasField("built"):
            doc["built"] = measure_doc(res.built)
    return doc


def stream_event(event: Any) -> Event:
    """A streamed ``*Event`` message as the document of its event."""
    kind = event.WhichOneof("event")
    if kind is None:
        raise ServerError("the server streamed an empty event")
    return {"event": kind, **_doc(getattr(event, kind))}


def _doc(msg: Message) -> dict[str, Any]:
    try:
        return message_doc(msg)
    except ValueError as exc:
        raise ServerError(f"the server's {type(msg).__name__} holds text that is not JSON: {exc}") from None


def _channel_options() -> list[tuple[str, int]]:
    # reconnect soon after a refused connection: the server listens only once its model is loaded
    return [
        ("grpc.max_receive_message_length", MAX_MESSAGE),
        ("grpc.max_send_message_length", MAX_MESSAGE),
        ("grpc.max_reconnect_backoff_ms", 2000),
    ]


class _Grpc(Generic[C]):
    _channel: C

    def __init__(
        self,
        target: str | None = None,
        timeout: float = DEFAULT_TIMEOUT,
        fit_timeout: float = FIT_TIMEOUT,
        retries: int = DEFAULT_RETRIES,
        *,
        retry: RetryPolicy | None = None,
    ) -> None:
        self.target = target or os.environ.get("BODYFIT_GRPC", DEFAULT_TARGET)
        self.timeout, self.fit_timeout, self.retries = timeout, fit_timeout, retries
        self.retry = retry_policy(retries, retry)
        self._channel = self._new_channel(self.target, options=_channel_options())
        self._stub = pb_grpc.BodyfitStub(self._channel)

    def _new_channel(self, target: str, options: list[tuple[str, int]]) -> C:
        raise NotImplementedError

    def _rpc(self, op: Operation[Any]) -> tuple[Callable[..., Any], Message, float]:
        """(the stub's method, the request, the deadline in seconds) of an operation."""
        if op.name not in RPCS:
            raise InvalidRequestError(
                f"{op.name} is served over REST only for now: use bodyfit.clients.Client"
            )
        timeout = self.fit_timeout if op.stream else self.timeout
        return getattr(self._stub, RPCS[op.name]), request_of(op), timeout


class GrpcClient(_Grpc[grpc.Channel], SyncClientCore):
    """Synchronous gRPC client.

    Args:
        target: "host:port" (default 127.0.0.1:50051, or $BODYFIT_GRPC).
        timeout: seconds for unary calls (fits get ``fit_timeout``).
        retries: attempts after the first, at most, when safe (see :class:`RetryPolicy`).
        retry: the retry policy (default :class:`RetryPolicy`: a 20 s budget); ``retries`` caps its count.
    """

    # a rig from several scans (``BuildSubject``)
    build_subject = sync_method(ops.build_subject)

    def _new_channel(self, target: str, options: list[tuple[str, int]]) -> grpc.Channel:
        return grpc.insecure_channel(target, options=options)

    def close(self) -> None:
        self._channel.close()

    def _send(self, op: Operation[Any]) -> Generator[Event, None, None]:
        rpc, request, timeout = self._rpc(op)
        try:
            if not op.stream:
                yield answer_event(op, rpc(request, timeout=timeout))
                return
            call = rpc(request, timeout=timeout)
            try:
                for event in call:
                    yield stream_event(event)
            finally:
                call.cancel()  # a no-op once the stream ended; stops it when the caller stopped reading
        except grpc.RpcError as exc:
            raise client_error(exc) from None


class AsyncGrpcClient(_Grpc[grpc.aio.Channel], AsyncClientCore):
    """Asynchronous gRPC client (grpc.aio); the same methods as :class:`GrpcClient`, awaited."""

    build_subject = async_method(ops.build_subject)

    def _new_channel(self, target: str, options: list[tuple[str, int]]) -> grpc.aio.Channel:
        return grpc.aio.insecure_channel(target, options=options)

    async def close(self) -> None:
        await self._channel.close()

    async def _close(self) -> None:
        await self.close()

    async def _send(self, op: Operation[Any]) -> AsyncGenerator[Event, None]:
        rpc, request, timeout = self._rpc(op)
        try:
            if not op.stream:
                yield answer_event(op, await rpc(request, timeout=timeout))
                return
            call = rpc(request, timeout=timeout)
            try:
                async for event in call:
                    yield stream_event(event)
            finally:
                call.cancel()
        except grpc.RpcError as exc:
            raise client_error(exc) from None

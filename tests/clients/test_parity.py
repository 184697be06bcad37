"""The four clients over fake transports: for the same answers, sync and async give identical results and
identical errors, and REST and gRPC give the same results (one core decodes both)."""

from __future__ import annotations

import asyncio
import base64
import dataclasses
import functools
import io
import json
from collections.abc import AsyncIterator, Callable, Iterator
from typing import Any

import grpc
import httpx
import numpy as np
import pytest

from bodyfit.api import bodyfit_pb2 as pb
from bodyfit.api.grpc_wire import to_proto
from bodyfit.clients.core import RetryPolicy
from bodyfit.clients.errors import BodyfitClientError
from bodyfit.clients.grpc_client import AsyncGrpcClient, GrpcClient
from bodyfit.clients.rest_client import AsyncClient, Client

NO_RETRY = RetryPolicy(retries=0)
RNG = np.random.default_rng(0)
F32 = {
    k: RNG.normal(size=s).astype(np.float32)
    for k, s in (
        ("vertices", (2, 4, 3)),
        ("joints", (2, 1, 3)),
        ("shape", (5,)),
        ("coordinates", (1,)),
        ("root", (3,)),
        ("v1", (4, 3)),
        ("j1", (1, 3)),
        ("seq_q", (3, 1)),
        ("seq_root", (3, 3)),
        ("seq_v", (3, 4, 3)),
        ("seq_j", (3, 1, 3)),
        ("err", (3,)),
        ("scales", (2, 3)),
        ("to_model", (4, 4)),
    )
}
FACES = np.array([[0, 1, 2], [1, 2, 3]], np.int32)
MODEL = {
    "dofs": [{"name": "knee_angle_r", "min": -0.1, "max": 2.0, "unit": "rad"}],
    "shape": {"n_bone": 2, "n_identity": 3},
    "mesh": {"n_vertices": 4, "n_faces": 2},
    "joint_names": ["pelvis"],
    "assets": {"format": "test", "sources": {"skin": "x"}, "sha256": {"skin": "ab"}},
    "version": "1",
}
PROGRESS: dict[str, Any] = {"stage": "fit", "done": 1, "total": 2, "message": "halfway"}
# complete documents, as the server sends them (bodyfit.wire reads them; tests/api/test_wire_models.py checks
# that the server's own answers match)
REPORT = {
    "distances": {"mean": 1.5, "median": 1.2, "p95": 3.0, "max": 4.5},
    "limit_violations": 0,
    "iterations": 40,
    "seconds": 0.25,
    "confident": True,
    "reasons": [],
    "extra": {
        "stage_loss_mm2": {"all": 2.25},
        "hints": {"up": {"value": "+z", "used": True, "how": "used as the scan's orientation"}},
    },
    "scan_to_model": {"mean": 2.0, "median": 1.2, "p95": 3.5, "max": 480.0},
    "model_to_scan": {"mean": 3.0, "median": 2.0, "p95": 9.0, "max": 260.0},
}
STATS = {
    "frames": 3,
    "seconds": 0.1,
    "fps": 30.0,
    "mean_mm": 1.5,
    "jitter_input_mm": None,
    "jitter_fit_mm": None,
    "jitter_ratio": None,
    "shape_keyframes": [0, 2],
    "jitter_note": "jitter needs three consecutive frames",
}
SUMMARY = {
    "path": "a",
    "frames": 3,
    "bad_frames": [1],
    "frame_rate": 30.0,
    "seconds": 0.2,
    "fps": 15.0,
    "v2v_mean_mm": 2.5,
    "v2v_max_frame_mm": 4.0,
    "limit_violations": 0,
    "max_frame_jump_deg": 3.5,
    "notes": [],
}
FILES = {"npz": b"PK\x03\x04", "mot": b"time\tknee\n"}


def b64(a: np.ndarray) -> dict[str, Any]:
    a = np.ascontiguousarray(a)
    return {"dtype": a.dtype.name, "shape": list(a.shape), "data": base64.b64encode(a.tobytes()).decode()}


# -- the same answers, once as REST bodies and once as gRPC messages --------------------------------------


def rest_answers() -> dict[str, Callable[[httpx.Request], httpx.Response]]:
    def npz(_: httpx.Request) -> httpx.Response:
        buf = io.BytesIO()
        np.savez(
            buf, vertices=F32["vertices"], joints=F32["joints"], joint_names=np.array(["pelvis"]), faces=FACES
        )
        return httpx.Response(200, content=buf.getvalue())

    def synth(request: httpx.Request) -> httpx.Response:
        body = json.loads(request.content)
        return npz(request) if body["format"] == "npz" else httpx.Response(200, content=b"ply\n")

    def ndjson(*events: dict[str, Any]) -> Callable[[httpx.Request], httpx.Response]:
        text = "".join(json.dumps(e) + "\n" for e in events)
        return lambda _: httpx.Response(
            200, content=text.encode(), headers={"content-type": "application/x-ndjson"}
        )

    seq_chunks = [
        {
            "event": "chunk",
            "start": s,
            "stop": e,
            "arrays": {
                "coordinates": b64(F32["seq_q"][s:e]),
                "root": b64(F32["seq_root"][s:e]),
                "vertices": b64(F32["seq_v"][s:e]),
                "joints": b64(F32["seq_j"][s:e]),
                "error_mm": b64(F32["err"][s:e]),
            },
        }
        for s, e in ((2, 3), (0, 2))  # out of order: the client sorts them
    ]
    up_chunk = {
        "event": "chunk",
        "start": 0,
        "stop": 3,
        "arrays": {
            "coordinates": b64(F32["seq_q"]),
            "root": b64(F32["seq_root"]),
            "joints": b64(F32["seq_j"]),
            "error_mm": b64(F32["err"]),
            "bad_frames": b64(np.array([False, True, False])),
        },
    }
    names = {"dof_names": ["knee_angle_r"], "joint_names": ["pelvis"]}
    return {
        "/v1/model": lambda _: httpx.Response(200, json=MODEL),
        "/v1/synthesize": synth,
        "/v1/fit/scan": ndjson(
            {"event": "progress", **PROGRESS},
            {
                "event": "result",
                "fitted_as": "registered",
                "report": REPORT,
                **names,
                "arrays": {
                    "shape": b64(F32["shape"]),
                    "coordinates": b64(F32["coordinates"]),
                    "root": b64(F32["root"]),
                    "vertices": b64(F32["v1"]),
                    "joints": b64(F32["j1"]),
                    "to_model": b64(F32["to_model"]),
                },
            },
        ),
        "/v1/fit/sequence": ndjson(
            {"event": "progress", **PROGRESS},
            *seq_chunks,
            {
                "event": "result",
                **names,
                "stats": STATS,
                "limit_violations": 2,
                "confident_frames": 3,
                "arrays": {"shape": b64(F32["shape"])},
            },
        ),
        "/v1/upgrade": ndjson(
            up_chunk,
            {
                "event": "result",
                **names,
                "segment_names": ["pelvis", "femur_r"],
                "summary": SUMMARY,
                "arrays": {"shape": b64(F32["shape"]), "scales": b64(F32["scales"])},
                "files": {k: base64.b64encode(v).decode() for k, v in FILES.items()},
            },
        ),
    }


def grpc_answers() -> dict[str, Callable[[Any], Any]]:
    a = {k: to_proto(v) for k, v in F32.items()}
    names = {"dof_names": ["knee_angle_r"], "joint_names": ["pelvis"]}

    def synth(request: pb.SynthesizeRequest) -> pb.SynthesizeResponse:
        if request.format == pb.ARRAYS:
            return pb.SynthesizeResponse(
                vertices=a["vertices"], joints=a["joints"], joint_names=["pelvis"], faces=to_proto(FACES)
            )
        return pb.SynthesizeResponse(data=b"ply\n", media_type="text/plain")

    seq = [
        pb.FitSequenceEvent(
            chunk=pb.SequenceChunk(
                start=s,
                stop=e,
                coordinates=to_proto(F32["seq_q"][s:e]),
                root=to_proto(F32["seq_root"][s:e]),
                vertices=to_proto(F32["seq_v"][s:e]),
                joints=to_proto(F32["seq_j"][s:e]),
                error_mm=to_proto(F32["err"][s:e]),
            )
        )
        for s, e in ((2, 3), (0, 2))
    ]
    progress = pb.Progress(**PROGRESS)
    return {
        "GetModelInfo": lambda _: pb.ModelInfo(
            version="1",
            dofs=[pb.Dof(name="knee_angle_r", min=-0.1, max=2.0, unit="rad")],
            n_bone=2,
            n_identity=3,
            n_vertices=4,
            n_faces=2,
            joint_names=["pelvis"],
            asset_format="test",
            asset_sources={"skin": "x"},
            asset_sha256={"skin": "ab"},
        ),
        "Synthesize": synth,
        "FitScan": lambda _: [
            pb.FitScanEvent(progress=progress),
            pb.FitScanEvent(
                result=pb.MeshFitResult(
                    fitted_as="registered",
                    shape=a["shape"],
                    coordinates=a["coordinates"],
                    root=a["root"],
                    vertices=a["v1"],
                    joints=a["j1"],
                    to_model=a["to_model"],
                    report_json=json.dumps(REPORT),
                    **names,
                )
            ),
        ],
        "FitSequence": lambda _: [
            pb.FitSequenceEvent(progress=progress),
            *seq,
            pb.FitSequenceEvent(
                result=pb.SequenceSummary(
                    shape=a["shape"],
                    stats_json=json.dumps(STATS),
                    limit_violations=2,
                    confident_frames=3,
                    dof_names=names["dof_names"],
                    joint_names=names["joint_names"],
                )
            ),
        ],
        "Upgrade": lambda _: [
            pb.UpgradeEvent(
                chunk=pb.UpgradeChunk(
                    start=0,
                    stop=3,
                    coordinates=a["seq_q"],
                    root=a["seq_root"],
                    joints=a["seq_j"],
                    error_mm=a["err"],
                    bad_frames=to_proto(np.array([False, True, False])),
                )
            ),
            pb.UpgradeEvent(
                result=pb.UpgradeSummary(
                    shape=a["shape"],
                    scales=a["scales"],
                    summary_json=json.dumps(SUMMARY),
                    files=FILES,
                    segment_names=["pelvis", "femur_r"],
                    **names,
                )
            ),
        ],
    }


class RpcFailure(grpc.RpcError):
    def __init__(
        self, code: grpc.StatusCode, details: str, trailing: tuple[tuple[str, str], ...] = ()
    ) -> None:
        self._code, self._details, self._trailing = code, details, trailing

    def code(self) -> grpc.StatusCode:
        return self._code

    def details(self) -> str:
        return self._details

    def trailing_metadata(self) -> tuple[tuple[str, str], ...]:
        return self._trailing


class FakeStub:
    """Answers each rpc from ``answers`` (a message, a list of streamed events, or an RpcError to raise),
    the sync or the grpc.aio way; records the requests."""

    def __init__(self, answers: dict[str, Callable[[Any], Any]], aio: bool) -> None:
        self.answers, self.aio = answers, aio
        self.requests: list[Any] = []

    def __getattr__(self, rpc: str) -> Callable[..., Any]:
        def call(request: Any, timeout: float) -> Any:
            self.requests.append(request)
            answer = self.answers[rpc](request)
            if isinstance(answer, list):
                return (AsyncStream if self.aio else SyncStream)(answer)
            if self.aio:
                return unary(answer)
            if isinstance(answer, Exception):
                raise answer
            return answer

        return call


async def unary(answer: Any) -> Any:
    if isinstance(answer, Exception):
        raise answer
    return answer


class SyncStream:
    def __init__(self, events: list[Any]) -> None:
        self.events = events

    def __iter__(self) -> Iterator[Any]:
        for event in self.events:
            if isinstance(event, Exception):
                raise event
            yield event

    def cancel(self) -> bool:
        return False


class AsyncStream(SyncStream):
    async def _events(self) -> AsyncIterator[Any]:
        for event in self:
            yield event

    def __aiter__(self) -> AsyncIterator[Any]:
        return self._events()


# -- running one script of calls through each client ------------------------------------------------------

CALLS: list[tuple[str, tuple[Any, ...], dict[str, Any]]] = [
    ("model_info", (), {}),
    ("synthesize", (), {"coordinates": {"knee_angle_r": [0.1, 0.2]}}),
    ("synthesize_file", ("ply",), {"coordinates": np.zeros((1, 1))}),
    ("fit_scan", (np.zeros((6, 3)),), {"up": "z", "facing": "+x", "pose": "Sitting", "height_m": 1.75}),
    ("fit_sequence", (F32["seq_v"],), {"chunk": 2}),
    ("upgrade", (b"PK\x03\x04",), {"height_m": 1.7}),
]


def outcome(call: Callable[[], Any]) -> Any:
    try:
        return call()
    except BodyfitClientError as exc:
        return exc


def run_sync(client: Any, calls: list[tuple[str, tuple[Any, ...], dict[str, Any]]]) -> list[Any]:
    results = []
    for name, args, kwargs in calls:
        events: list[dict[str, Any]] = []
        extra = {"progress": events.append} if name.startswith(("fit", "upgrade")) else {}
        results.append((outcome(functools.partial(getattr(client, name), *args, **kwargs, **extra)), events))
    return results


def run_async(make: Callable[[], Any], calls: list[tuple[str, tuple[Any, ...], dict[str, Any]]]) -> list[Any]:
    async def main() -> list[Any]:
        results = []
        async with make() as client:
            for name, args, kwargs in calls:
                events: list[dict[str, Any]] = []
                extra = {"progress": events.append} if name.startswith(("fit", "upgrade")) else {}
                try:
                    results.append((await getattr(client, name)(*args, **kwargs, **extra), events))
                except BodyfitClientError as exc:
                    results.append((exc, events))
        return results

    return asyncio.run(main())


def same(a: Any, b: Any) -> bool:
    """Equal results (arrays equal in dtype and value) or equal errors (type, message and fields)."""
    if isinstance(a, BodyfitClientError):
        return type(a) is type(b) and (str(a), a.status, a.field, a.retry_after, a.sent) == (
            str(b),
            b.status,
            b.field,
            b.retry_after,
            b.sent,
        )
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        return type(a) is type(b) and all(
            same(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a)
        )
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.dtype == b.dtype and np.array_equal(a, b)
    if isinstance(a, tuple | list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    return bool(a == b)


def rest_pair(handlers: dict[str, Callable[[httpx.Request], httpx.Response]]) -> tuple[list[Any], list[Any]]:
    def route(request: httpx.Request) -> httpx.Response:
        return handlers[request.url.path](request)

    transport = httpx.MockTransport(route)
    sync = run_sync(
        Client(http_client=httpx.Client(transport=transport, base_url="http://t"), retry=NO_RETRY), CALLS
    )

    def make() -> AsyncClient:
        http = httpx.AsyncClient(transport=transport, base_url="http://t")
        return AsyncClient(http_client=http, retry=NO_RETRY)

    return sync, run_async(make, CALLS)


def grpc_pair(answers: dict[str, Callable[[Any], Any]]) -> tuple[list[Any], list[Any], FakeStub, FakeStub]:
    sync_stub, async_stub = FakeStub(answers, aio=False), FakeStub(answers, aio=True)
    with GrpcClient("127.0.0.1:1", retry=NO_RETRY) as client:
        client._stub = sync_stub  # type: ignore[assignment]
        sync = run_sync(client, CALLS)

    def make() -> AsyncGrpcClient:
        client = AsyncGrpcClient("127.0.0.1:1", retry=NO_RETRY)
        client._stub = async_stub  # type: ignore[assignment]
        return client

    return sync, run_async(make, CALLS), sync_stub, async_stub


# -- the tests ---------------------------------------------------------------------------------------------


def test_rest_sync_and_async_give_identical_results() -> None:
    sync, aio = rest_pair(rest_answers())
    assert same(sync, aio)
    info, synth, ply, scan, seq, up = (r for r, _ in sync)
    assert ply == b"ply\n"
    assert info.dof_names == ("knee_angle_r",) and info.n_shape == 5
    assert synth.vertices.dtype == np.float32 and np.array_equal(synth.faces, FACES)
    assert scan.confident and sync[3][1] == [PROGRESS]
    assert np.array_equal(scan.to_model, F32["to_model"]) and scan.report["scan_to_model"]["max"] == 480.0
    assert scan.report["extra"]["hints"]["up"]["used"] is True
    assert np.array_equal(seq.coordinates, F32["seq_q"]) and seq.limit_violations == 2
    assert seq.confident_frames == 3
    assert up.files == FILES and up.bad_frames.tolist() == [False, True, False]


def test_grpc_sync_and_async_give_identical_results_and_requests() -> None:
    sync, aio, sync_stub, async_stub = grpc_pair(grpc_answers())
    assert same(sync, aio)
    assert sync_stub.requests == async_stub.requests and len(sync_stub.requests) == len(CALLS)
    upgrade = sync_stub.requests[-1]
    assert upgrade.HasField("height_m") and not upgrade.HasField("sex") and upgrade.filename == "sequence.npz"
    scan = sync_stub.requests[3]  # the hints in their canonical spelling; those not given are unset
    assert (scan.up, scan.facing, scan.pose, scan.height_m) == ("+z", "+x", "sitting", 1.75)
    assert not scan.HasField("sex")


def test_rest_and_grpc_decode_to_the_same_results() -> None:
    rest, _ = rest_pair(rest_answers())
    over_grpc, *_ = grpc_pair(grpc_answers())
    for (a, a_events), (b, b_events) in zip(rest, over_grpc, strict=True):
        assert same(a, b), type(a).__name__
        assert a_events == b_events


def problem(status: int, kind: str, detail: str, field: str | None = None, **headers: str) -> httpx.Response:
    doc = {"kind": kind, "detail": detail, "status": status, **({"field": field} if field else {})}
    return httpx.Response(status, json=doc, headers={"content-type": "application/problem+json", **headers})


def test_rest_sync_and_async_raise_identical_errors() -> None:
    def stream(*lines: str) -> Callable[[httpx.Request], httpx.Response]:
        return lambda _: httpx.Response(200, content="".join(line + "\n" for line in lines).encode())

    handlers = {
        "/v1/model": lambda _: problem(503, "unavailable", "still loading", **{"retry-after": "5"}),
        "/v1/synthesize": lambda _: problem(422, "invalid_argument", "out of range", "coordinates"),
        "/v1/fit/scan": lambda _: httpx.Response(502, text="<html>Bad Gateway</html>"),  # a proxy's answer
        "/v1/fit/sequence": stream(
            json.dumps({"event": "progress", **PROGRESS}),
            json.dumps(
                {
                    "event": "error",
                    "kind": "invalid_argument",
                    "detail": "NaN",
                    "field": "frames",
                    "status": 422,
                }
            ),
        ),
        "/v1/upgrade": stream(json.dumps({"event": "progress", **PROGRESS})),  # cut before its result
    }
    sync, aio = rest_pair(handlers)
    assert same(sync, aio)
    kinds = [type(r).__name__ for r, _ in sync]
    assert kinds == [
        "ServerBusyError",
        "InvalidRequestError",
        "InvalidRequestError",
        "ServerError",
        "InvalidRequestError",
        "ServerError",
    ]
    assert sync[0][0].retry_after == 5.0 and sync[1][0].field == "coordinates" and sync[1][0].status == 422
    assert "HTTP 502" in str(sync[3][0]) and sync[3][0].status == 502
    assert sync[4][1] == [PROGRESS] and sync[4][0].field == "frames" and "without a result" in str(sync[5][0])


def test_grpc_sync_and_async_raise_identical_errors() -> None:
    invalid = RpcFailure(
        grpc.StatusCode.INVALID_ARGUMENT,
        "out of range",
        (("bodyfit-kind", "invalid_argument"), ("bodyfit-field", "coordinates")),
    )
    answers = {
        "GetModelInfo": lambda _: RpcFailure(grpc.StatusCode.UNAVAILABLE, "failed to connect to all"),
        "Synthesize": lambda _: invalid,
        "FitScan": lambda _: [
            RpcFailure(grpc.StatusCode.RESOURCE_EXHAUSTED, "Concurrent RPC limit exceeded")
        ],
        "FitSequence": lambda _: [
            pb.FitSequenceEvent(progress=pb.Progress(**PROGRESS)),
            RpcFailure(grpc.StatusCode.DEADLINE_EXCEEDED, "Deadline Exceeded"),
        ],
        "Upgrade": lambda _: [pb.UpgradeEvent(progress=pb.Progress(**PROGRESS))],
    }
    sync, aio, *_ = grpc_pair(answers)
    assert same(sync, aio)
    kinds = [type(r).__name__ for r, _ in sync]
    assert kinds == [
        "ConnectionFailedError",
        "InvalidRequestError",
        "InvalidRequestError",
        "ServerBusyError",
        "RequestTimeoutError",
        "ServerError",
    ]
    assert (
        not sync[0][0].sent and sync[1][0].field == "coordinates" and sync[1][0].status == "INVALID_ARGUMENT"
    )
    assert sync[4][1] == [PROGRESS] and "without a result" in str(sync[5][0])


def test_a_format_the_server_cannot_write_is_refused_before_sending() -> None:
    sent: list[httpx.Request] = []

    def handler(request: httpx.Request) -> httpx.Response:
        sent.append(request)
        return httpx.Response(200)

    transport = httpx.MockTransport(handler)
    with (
        Client("http://t", http_client=httpx.Client(transport=transport)) as c,
        pytest.raises(ValueError, match="format must be one of npz, ply, obj, glb, json"),
    ):
        c.synthesize_file("stl")
    assert sent == []


def test_scan_hints_travel_as_the_same_fields_over_rest_and_grpc() -> None:
    """REST sends the hints as form fields named as gRPC's FitScanRequest fields, with the same values;
    hints not given are not sent."""
    fields: list[dict[str, str]] = []

    def fit(request: httpx.Request) -> httpx.Response:
        body = request.read().decode("latin-1")
        parts = [p for p in body.split("Content-Disposition: form-data; ") if p.startswith("name=")]
        form = {p.split('"')[1]: p.split("\r\n\r\n", 1)[1].split("\r\n", 1)[0] for p in parts}
        fields.append({k: v for k, v in form.items() if k != "file"})
        return rest_answers()["/v1/fit/scan"](request)

    handlers = {**rest_answers(), "/v1/fit/scan": fit}
    rest_pair(handlers)
    *_, stub, _ = grpc_pair(grpc_answers())
    sent = stub.requests[3]
    expected = {"units": "auto", "up": "+z", "facing": "+x", "pose": "sitting", "height_m": "1.75"}
    assert fields == [expected, expected]  # sync and async
    assert {k: str(getattr(sent, k)) for k in expected} == expected and not sent.HasField("sex")


@pytest.mark.parametrize(
    ("hints", "words"),
    [
        ({"up": "q"}, "up must be one of +x, -x, +y, -y, +z, -z"),
        ({"up": "+y", "facing": "sideways"}, "facing must be one of +x, -x, +y, -y, +z, -z"),
        ({"pose": "kneeling"}, "pose must be one of standing, sitting, a-pose, t-pose"),
    ],
)
def test_a_hint_that_names_no_allowed_value_is_refused_before_sending(
    hints: dict[str, Any], words: str
) -> None:
    sent: list[httpx.Request] = []

    def handler(request: httpx.Request) -> httpx.Response:
        sent.append(request)
        return httpx.Response(200)

    transport = httpx.MockTransport(handler)
    with (
        Client("http://t", http_client=httpx.Client(transport=transport)) as c,
        pytest.raises(ValueError, match=words.replace("+", "\\+")),
    ):
        c.fit_scan(np.zeros((6, 3)), **hints)
    assert sent == []


def test_the_four_clients_have_the_same_methods_and_signatures() -> None:
    import inspect

    names = (
        "model_info",
        "synthesize",
        "synthesize_file",
        "fit_scan",
        "fit_sequence",
        "upgrade",
        "measure",
        "build_subject",
    )
    for name in names:
        signatures = {
            str(inspect.signature(getattr(cls, name)))
            for cls in (Client, AsyncClient, GrpcClient, AsyncGrpcClient)
        }
        assert len(signatures) == 1, (name, signatures)
        assert inspect.iscoroutinefunction(getattr(AsyncClient, name))
        assert not inspect.iscoroutinefunction(getattr(Client, name))
    synthesize = inspect.signature(Client("http://t").synthesize)
    assert list(synthesize.parameters) == [
        "shape", "coordinates", "root", "skeleton", "faces", "batch", "measurements", "sex", "subject"
    ]  # fmt: skip
    assert synthesize.return_annotation.__name__ == "Synthesis"

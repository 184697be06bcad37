"""The gRPC transport on 127.0.0.1 through the gRPC SDK: parity with the core, streaming, statuses with
the field at fault, health, reflection, cancellation; the generated modules match the .proto."""

from __future__ import annotations

import asyncio
import io
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc

from bodyfit.api import bodyfit_pb2 as pb
from bodyfit.api import bodyfit_pb2_grpc as pb_grpc
from bodyfit.api.grpc_server import create_grpc_server
from bodyfit.api.grpc_wire import to_proto
from bodyfit.api.settings import ServiceSettings
from bodyfit.clients.errors import (
    InvalidRequestError,
    RequestTimeoutError,
    RequestTooLargeError,
    ServerBusyError,
)
from bodyfit.clients.grpc_client import AsyncGrpcClient, GrpcClient
from bodyfit.service.core import BodyService, SynthRequest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def target(body_service: BodyService) -> Iterator[str]:
    server, port = create_grpc_server(body_service, "127.0.0.1:0", ServiceSettings(max_upload_mb=4.0))
    server.start()
    yield f"127.0.0.1:{port}"
    server.stop(grace=1).wait()


@pytest.fixture(scope="module")
def client(target: str) -> Iterator[GrpcClient]:
    with GrpcClient(target, retries=0) as c:
        yield c


def test_model_info(client: GrpcClient, body_service: BodyService) -> None:
    info = client.model_info()
    assert info.dof_names == body_service.info().dof_names and info.n_shape == 32
    assert np.array_equal(info.dof_ranges, body_service.info().dof_ranges)


def test_synthesize_matches_the_core(client: GrpcClient, body_service: BodyService) -> None:
    rng = np.random.default_rng(3)
    shape = rng.normal(size=(2, 32))
    out = client.synthesize(shape=shape, coordinates={"knee_angle_r": [0.2, 1.0]}, faces=True, skeleton=True)
    q = body_service.model.skeleton.coordinates({"knee_angle_r": np.array([0.2, 1.0])})
    ref = body_service.synthesize(SynthRequest(shape=shape, coordinates=q))
    assert np.abs(out.vertices - ref.vertices).max() < 1e-6 and out.joint_names == ref.joint_names
    assert out.faces is not None and out.faces.shape == (26692, 3)
    assert out.bones is not None and out.bones.shape[0] == 2
    for fmt, magic in (("ply", b"ply"), ("glb", b"glTF"), ("npz", b"PK")):
        assert client.synthesize_file(fmt).startswith(magic)


@pytest.mark.parametrize(
    ("kwargs", "error", "field", "words"),
    [
        ({"coordinates": {"knee_angl_r": 1.0}}, InvalidRequestError, "coordinates", "knee_angle_r"),
        ({"coordinates": {"knee_angle_r": 3.0}}, InvalidRequestError, "coordinates", "range"),
        ({"shape": np.full((1, 32), np.nan)}, InvalidRequestError, "shape", "NaN"),
        ({"root": np.zeros((1, 2))}, InvalidRequestError, "root", "(1, 3)"),
        ({"batch": 100_000}, RequestTooLargeError, "batch", "split"),
        ({"root": np.array([[0.0, 1e308, 0.0]])}, InvalidRequestError, "root", "[-100, 100]"),
        ({"shape": np.full((1, 32), 1e6)}, InvalidRequestError, "shape", "[-10, 10]"),
        ({"shape": np.zeros((0, 32))}, InvalidRequestError, "shape", "0 bodies"),
    ],
)
def test_errors_name_the_field(
    client: GrpcClient, kwargs: dict[str, Any], error: type[Exception], field: str, words: str
) -> None:
    with pytest.raises(error) as err:
        client.synthesize(**kwargs)
    assert getattr(err.value, "field", None) == field and words in str(err.value)


def test_malformed_arrays_are_invalid_argument(target: str) -> None:
    with grpc.insecure_channel(target) as channel:
        stub = pb_grpc.BodyfitStub(channel)
        for array, words in (
            (pb.Array(dtype="float32", shape=[1, 46], data=b"\x00" * 10), "need 184"),
            (pb.Array(dtype="complex64", shape=[1, 46]), "dtype"),
            (pb.Array(dtype="float64", shape=[-1, 46]), "negative"),
            (pb.Array(dtype="float64", shape=[0, 2**62]), "declares a size above"),
            (pb.Array(dtype="float64", shape=[1] * 9, data=b"\x00" * 8), "dimensions"),
            (to_proto(np.zeros((1, 46), np.int32)), "floats"),
            (to_proto(np.zeros((1, 46), bool)), "floats"),
        ):
            with pytest.raises(grpc.RpcError) as err:
                stub.Synthesize(pb.SynthesizeRequest(coordinates=array), timeout=10)
            assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and words in err.value.details()
            assert dict(err.value.trailing_metadata())["bodyfit-field"] == "coordinates"
        with pytest.raises(grpc.RpcError) as err:
            list(stub.FitScan(pb.FitScanRequest(data=b"garbage", format="ply"), timeout=10))
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "PLY" in err.value.details()
        with pytest.raises(grpc.RpcError) as err:
            list(stub.FitSequence(pb.FitSequenceRequest(frames=to_proto(np.zeros((2, 5, 3)))), timeout=10))
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "13348" in err.value.details()


@pytest.mark.parametrize(
    ("frames", "words"),
    [
        (np.zeros((2, 13348, 3), np.int32), "floats"),
        (np.zeros((2, 13348, 3), bool), "floats"),
        (np.zeros((3, 13348, 3), np.float32), "frame 0 holds only zeros"),
        (np.full((3, 13348, 3), 0.5, np.float32), "one point"),
    ],
    ids=["int32", "bool", "all zero", "constant"],
)
def test_fit_sequence_refuses_what_rest_refuses(target: str, frames: np.ndarray, words: str) -> None:
    """int and bool frames (which REST refuses from an npz) and frames that cannot be bodies:
    INVALID_ARGUMENT naming the frames, before any progress event."""
    with grpc.insecure_channel(target) as channel, pytest.raises(grpc.RpcError) as err:
        list(
            pb_grpc.BodyfitStub(channel).FitSequence(
                pb.FitSequenceRequest(frames=to_proto(frames)), timeout=10
            )
        )
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and words in err.value.details()
    assert dict(err.value.trailing_metadata())["bodyfit-field"] == "frames"


def test_zero_bodies_in_a_file_format_are_invalid(target: str) -> None:
    with grpc.insecure_channel(target) as channel, pytest.raises(grpc.RpcError) as err:
        pb_grpc.BodyfitStub(channel).Synthesize(
            pb.SynthesizeRequest(shape=to_proto(np.zeros((0, 32))), format=pb.GLB), timeout=10
        )
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "0 bodies" in err.value.details()


def test_scan_errors_are_invalid_argument_in_the_stream(
    client: GrpcClient, body_service: BodyService, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A scan in metres sent as millimetres, and a model-layer input error raised by the fit itself (the
    scan fitter's ScanError): INVALID_ARGUMENT, and the SDK's InvalidRequestError, never INTERNAL."""
    from bodyfit.io.scans import ScanError

    points = np.random.default_rng(0).uniform([-0.2, 0.0, -0.15], [0.2, 1.7, 0.15], (2000, 3))
    buf = io.BytesIO()
    np.savez(buf, points=points)
    with pytest.raises(InvalidRequestError, match="units=mm") as bad:
        client.fit_scan(buf.getvalue(), format="npz", units="mm")
    assert bad.value.field == "units"

    def fit_mesh(*args: object, **kwargs: object) -> None:
        raise ScanError("only 4 points are left after thinning to a 1 cm grid")

    monkeypatch.setattr(body_service, "fit_mesh", fit_mesh)
    with pytest.raises(InvalidRequestError, match="only 4 points") as err:
        client.fit_scan(buf.getvalue(), format="npz")
    assert err.value.status == "INVALID_ARGUMENT"


def test_fit_scan_streams_progress_then_the_result(client: GrpcClient, body_service: BodyService) -> None:
    verts = body_service.synthesize(SynthRequest(coordinates={"hip_flexion_r": 0.6})).vertices[0]
    buf = io.BytesIO()
    np.savez(buf, points=verts)
    events: list[dict[str, Any]] = []
    fit = client.fit_scan(buf.getvalue(), format="npz", progress=events.append)
    assert fit.fitted_as == "registered" and fit.confident and fit.report["distances"]["mean"] < 2.0
    hip = fit.dof_names.index("hip_flexion_r")
    assert abs(fit.coordinates[hip] - 0.6) < 0.05 and events[-1]["message"] == "done"


def test_fit_scan_takes_points(client: GrpcClient, body_service: BodyService) -> None:
    verts = body_service.synthesize(SynthRequest(coordinates={"hip_flexion_r": 0.6})).vertices[0]
    fit = client.fit_scan(verts)
    assert fit.fitted_as == "registered" and fit.report["distances"]["mean"] < 2.0


def test_fit_sequence_reassembles_chunks(client: GrpcClient, body_service: BodyService) -> None:
    knee = np.linspace(0.1, 1.0, 5)
    frames = body_service.synthesize(SynthRequest(coordinates={"knee_angle_l": knee})).vertices
    seq = client.fit_sequence(frames, chunk=2)
    assert seq.coordinates.shape == (5, 46) and seq.vertices.shape == (5, 13348, 3)
    assert np.abs(seq.coordinates[:, seq.dof_names.index("knee_angle_l")] - knee).max() < 0.1
    assert seq.limit_violations == 0 and seq.stats["frames"] == 5 and seq.confident_frames == 5


def test_health_and_reflection(target: str) -> None:
    with grpc.insecure_channel(target) as channel:
        health = health_pb2_grpc.HealthStub(channel)
        for service in ("", "bodyfit.v1.Bodyfit"):
            answer = health.Check(health_pb2.HealthCheckRequest(service=service), timeout=5)
            assert answer.status == health_pb2.HealthCheckResponse.SERVING
        stub = reflection_pb2_grpc.ServerReflectionStub(channel)
        request = reflection_pb2.ServerReflectionRequest(list_services="")
        answer = next(iter(stub.ServerReflectionInfo(iter([request]), timeout=5)))
        names = {s.name for s in answer.list_services_response.service}
        assert "bodyfit.v1.Bodyfit" in names and "grpc.health.v1.Health" in names


def test_a_cancelled_stream_stops_and_the_server_keeps_serving(
    target: str, body_service: BodyService
) -> None:
    # 28 frames: the fit still runs when the client cancels (cancel() is False on a finished call), and the
    # request stays under the server's 5 MiB message limit
    frames = body_service.synthesize(SynthRequest(batch=28)).vertices
    with grpc.insecure_channel(target) as channel:
        stub = pb_grpc.BodyfitStub(channel)
        call = stub.FitSequence(pb.FitSequenceRequest(frames=to_proto(frames)), timeout=60)
        first = next(call)
        assert first.WhichOneof("event") == "progress"
        assert call.cancel()
        with pytest.raises(grpc.RpcError) as err:
            list(call)
        assert err.value.code() == grpc.StatusCode.CANCELLED
    # The worker slot is released once the fit sees the cancellation (at its next chunk: later on a loaded
    # machine), so the next fit may first be told the server is busy; it must get through in the end.
    deadline = time.monotonic() + 120
    with GrpcClient(target, retries=0) as c:
        while True:
            try:
                assert c.fit_sequence(frames[:3]).coordinates.shape == (3, 46)
                break
            except ServerBusyError:
                assert time.monotonic() < deadline, "the cancelled fit never released its worker slot"


def test_a_client_deadline_is_a_typed_timeout(target: str, body_service: BodyService) -> None:
    frames = body_service.synthesize(SynthRequest(batch=4)).vertices
    with GrpcClient(target, fit_timeout=0.05) as c, pytest.raises(RequestTimeoutError):
        c.fit_sequence(frames)


def test_async_client(target: str) -> None:
    async def run() -> tuple[int, tuple[int, ...]]:
        async with AsyncGrpcClient(target) as c:
            info = await c.model_info()
            out = await c.synthesize(batch=2)
            with pytest.raises(InvalidRequestError):
                await c.synthesize(shape=np.zeros((1, 3)))
            return info.n_vertices, out.vertices.shape

    assert asyncio.run(run()) == (13348, (2, 13348, 3))


def test_generated_modules_match_the_proto(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHON": sys.executable}  # this interpreter's grpcio-tools, whatever the venv
    subprocess.run([str(ROOT / "scripts" / "gen_proto.sh"), str(tmp_path)], check=True, cwd=ROOT, env=env)
    for name in ("bodyfit_pb2.py", "bodyfit_pb2.pyi", "bodyfit_pb2_grpc.py"):
        assert (tmp_path / name).read_text() == (ROOT / "bodyfit" / "api" / name).read_text(), (
            f"{name} is stale: run scripts/gen_proto.sh"
        )


def test_upgrade_over_grpc(client: GrpcClient, target: str, tmp_path: Path) -> None:
    sequence = ROOT / "tests" / "data" / "smpl_format" / "cmu_131_smpl.npz"
    out = client.upgrade(sequence, chunk=16)
    assert out.coordinates.shape == (60, 46) and out.summary["path"] == "a"
    assert out.summary["limit_violations"] == 0 and set(out.files) == {"npz", "json", "osim", "mot"}
    assert len(out.segment_names) == len(out.scales) > 10 and "pelvis" in out.segment_names
    assert np.allclose(np.load(out.save(tmp_path, "walk")["npz"])["coordinates"], out.coordinates)
    hinted = client.upgrade(sequence, height_m=1.7)  # the hints reach the server (path a ignores them)
    assert any("hints were not used" in note for note in hinted.summary["notes"])
    given = client.upgrade(sequence, up="+y")  # the up axis reaches the server and is reported as given
    assert given.summary["up_axis"] == "+y" and given.summary["up_given"] is True
    with grpc.insecure_channel(target) as channel, pytest.raises(grpc.RpcError) as err:
        stub = pb_grpc.BodyfitStub(channel)
        list(stub.Upgrade(pb.UpgradeRequest(data=b"", filename="walk.npz", up="sideways"), timeout=10))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "up" in err.value.details()
    with pytest.raises(InvalidRequestError, match="sex must be one of") as bad:
        client.upgrade(sequence, sex="robot")
    assert bad.value.field == "sex"
    with grpc.insecure_channel(target) as channel, pytest.raises(grpc.RpcError) as err:
        list(
            pb_grpc.BodyfitStub(channel).Upgrade(
                pb.UpgradeRequest(data=b"\x80", filename="walk.pkl"), timeout=10
            )
        )
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "unpickle" in err.value.details()

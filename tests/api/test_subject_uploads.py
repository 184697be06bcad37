"""``subject=`` over REST and gRPC, through both SDK clients: synthesis, scan and sequence fits and upgrades
with a subject file, the BuildSubject rpc, and subject files that cannot be used (damaged, another model's,
not an npz, or sent with shape parameters) refused with 422 / INVALID_ARGUMENT naming the field and the fix;
the subject field of every route fuzzed with arbitrary and corrupted files."""

from __future__ import annotations

import base64
import io
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import pytest
import torch
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bodyfit.api import bodyfit_pb2 as pb
from bodyfit.api import bodyfit_pb2_grpc as pb_grpc
from bodyfit.api.grpc_server import create_grpc_server
from bodyfit.api.rest.app import create_app
from bodyfit.api.settings import ServiceSettings
from bodyfit.clients.errors import InvalidRequestError
from bodyfit.clients.grpc_client import GrpcClient
from bodyfit.clients.rest_client import Client
from bodyfit.models.rig.subject import Subject
from bodyfit.service.core import BodyService, SynthRequest
from tests.service.subject_files import damaged, make_subject

SEQUENCE = Path(__file__).resolve().parents[1] / "data" / "smpl_format" / "cmu_131_smpl.npz"
BEND = {"knee_angle_r": 0.5, "elbow_flex_l": 0.9}


@pytest.fixture(scope="module")
def subject(body_service: BodyService) -> Subject:
    return make_subject(body_service.model, seed=4)


@pytest.fixture(scope="module")
def http(body_service: BodyService) -> Iterator[TestClient]:
    app = create_app(ServiceSettings(max_upload_mb=8.0), service=body_service)
    with TestClient(app, raise_server_exceptions=False) as c:
        yield c


@pytest.fixture(scope="module")
def sdk(body_service: BodyService) -> Iterator[Client]:
    """The REST SDK on an in-process server of its own (closing the client closes its transport)."""
    app = create_app(ServiceSettings(max_upload_mb=8.0), service=body_service)
    with Client("http://testserver", http_client=TestClient(app)) as c:
        yield c


@pytest.fixture(scope="module")
def target(body_service: BodyService) -> Iterator[str]:
    server, port = create_grpc_server(body_service, "127.0.0.1:0", ServiceSettings(max_upload_mb=8.0))
    server.start()
    yield f"127.0.0.1:{port}"
    server.stop(grace=1).wait()


def posed(body_service: BodyService, subject: Subject, bend: np.ndarray) -> np.ndarray:
    """(B, V, 3) float64: the subject posed by ``bend`` (B,), the share of :data:`BEND` at the right knee
    and left elbow."""
    q = body_service.model.skeleton.coordinates({name: bend * value for name, value in BEND.items()})
    return body_service.synthesize(SynthRequest(coordinates=q, subject=subject.to_bytes())).vertices.astype(
        np.float64
    )


def short_sequence(frames: int = 8) -> bytes:
    """The test clip's first ``frames`` frames, as an AMASS-style .npz."""
    with np.load(SEQUENCE) as npz:
        arrays = {k: npz[k] for k in npz.files}
    for key in ("poses", "trans"):
        arrays[key] = arrays[key][:frames]
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def subject_scales(body_service: BodyService, subject: Subject) -> np.ndarray:
    """(n_seg, 3) the bone scales of the subject's own decoder."""
    model = body_service.model
    with torch.no_grad():
        c = torch.as_tensor(subject.shape[None], dtype=torch.float32)
        q = torch.zeros(1, model.skeleton.n_dof)
        return subject.decoder(model, torch.float32)(c, q, torch.zeros(1, 3))[3].numpy()[0]


# -- REST and the REST SDK ---------------------------------------------------------------------------------
def test_rest_synthesis_with_a_subject(
    http: TestClient, sdk: Client, body_service: BodyService, subject: Subject
) -> None:
    """The subject as base64 in the JSON body, and through the SDK as a Subject: the core's bodies."""
    data = subject.to_bytes()
    body = {"coordinates": {k: [v] for k, v in BEND.items()}, "subject": base64.b64encode(data).decode()}
    r = http.post("/v1/synthesize", json=body)
    assert r.status_code == 200, r.text
    with np.load(io.BytesIO(r.content)) as npz:
        vertices = npz["vertices"]
    assert np.array_equal(vertices[0], posed(body_service, subject, np.array([1.0]))[0].astype(np.float32))
    out = sdk.synthesize(coordinates={k: [v] for k, v in BEND.items()}, subject=subject)
    assert np.array_equal(out.vertices, vertices)


def test_rest_fits_with_a_subject_through_the_sdk(
    sdk: Client, body_service: BodyService, subject: Subject, tmp_path: Path
) -> None:
    meshes = posed(body_service, subject, np.array([0.3, 0.6, 0.9]))
    path = subject.save(tmp_path / "subject.npz")
    fit = sdk.fit_scan(meshes[0], subject=path)
    sequence = sdk.fit_sequence(meshes, subject=subject.to_bytes(), chunk=2)
    assert fit.fitted_as == "registered" and np.allclose(fit.shape, subject.shape, atol=1e-6)
    assert fit.report["distances"]["mean"] < 0.5
    assert np.allclose(sequence.shape, subject.shape, atol=1e-6) and sequence.error_mm.mean() < 2.0


@pytest.mark.parametrize("what", ["truncated", "text", "other npz", "empty"])
def test_rest_refuses_unusable_subjects(http: TestClient, subject: Subject, what: str) -> None:
    broken = dict(damaged(subject.to_bytes()))[what]
    scan = {"file": ("scan.npz", _points_npz(np.zeros((10, 3))))}
    answers = [
        http.post("/v1/synthesize", json={"subject": base64.b64encode(broken).decode()}),
        http.post("/v1/fit/scan", files={**scan, "subject": ("s.npz", broken)}),
        http.post("/v1/fit/sequence", files={"file": ("f.npz", b"x"), "subject": ("s.npz", broken)}),
        http.post("/v1/upgrade", files={"file": ("u.npz", b"x"), "subject": ("s.npz", broken)}),
    ]
    for r in answers:
        assert r.status_code == 422, r.text
        problem = r.json()
        assert problem["field"] == "subject" and "bodyfit rig" in problem["detail"], problem


def test_rest_refuses_another_models_subject_and_shape_with_a_subject(
    http: TestClient, sdk: Client, subject: Subject
) -> None:
    foreign = Subject(subject.shape, subject.offsets, "f" * 64, subject.poses, subject.roots)
    r = http.post("/v1/synthesize", json={"subject": base64.b64encode(foreign.to_bytes()).decode()})
    assert r.status_code == 422 and "another body model" in r.json()["detail"]
    body = {"subject": base64.b64encode(subject.to_bytes()).decode(), "shape": [[0.0] * 32]}
    r = http.post("/v1/synthesize", json=body)
    assert r.status_code == 422 and r.json()["field"] == "shape" and "drop shape" in r.json()["detail"]
    files = {"file": ("u.npz", short_sequence()), "subject": ("s.npz", subject.to_bytes())}
    r = http.post("/v1/upgrade", files=files, data={"sex": "male"})
    assert r.status_code == 422 and "give a subject or shape hints" in r.json()["detail"]
    with pytest.raises(ValueError, match="not both"):
        sdk.synthesize(shape=np.zeros((1, 32)), subject=subject)


def _points_npz(points: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, points=points)
    return buffer.getvalue()


def _mutated(data: bytes) -> st.SearchStrategy[bytes]:
    """Arbitrary bytes, and the subject file cut at any point or with any one byte changed."""
    cut = st.integers(0, len(data) - 1).map(lambda n: data[:n])
    flip = st.tuples(st.integers(0, len(data) - 1), st.integers(1, 255)).map(
        lambda p: data[: p[0]] + bytes([data[p[0]] ^ p[1]]) + data[p[0] + 1 :]
    )
    return st.one_of(st.binary(max_size=2048), cut, flip)


@pytest.mark.parametrize("route", ["/v1/synthesize", "/v1/fit/scan", "/v1/fit/sequence", "/v1/upgrade"])
def test_fuzzed_subject_files_never_fail_the_server(http: TestClient, subject: Subject, route: str) -> None:
    """Whatever the subject field holds, no route answers 5xx; a refusal is a problem document, and a
    refused subject is named as the field at fault. (Every other input is one the route refuses at once,
    so that a subject that still reads starts no work.)"""
    data = subject.to_bytes()

    @given(broken=_mutated(data))
    @settings(max_examples=30, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
    def check(broken: bytes) -> None:
        if route == "/v1/synthesize":
            body = {"subject": base64.b64encode(broken).decode(), "coordinates": {"knee_angle_r": [9.0]}}
            r = http.post(route, json=body)
        else:
            r = http.post(route, files={"file": ("f.npz", b"not a file"), "subject": ("s.npz", broken)})
        assert r.status_code == 422, r.text
        assert r.headers["content-type"].startswith("application/problem+json") and r.json()["detail"]

    check()


# -- gRPC and the gRPC SDK ---------------------------------------------------------------------------------
def test_grpc_synthesis_fit_and_upgrade_with_a_subject(
    target: str, body_service: BodyService, subject: Subject
) -> None:
    meshes = posed(body_service, subject, np.array([0.3, 0.7]))
    with GrpcClient(target, retries=0) as sdk:
        out = sdk.synthesize(coordinates={k: [v] for k, v in BEND.items()}, subject=subject)
        fit = sdk.fit_scan(meshes[1], subject=subject)
        upgraded = sdk.upgrade(short_sequence(), subject=subject.to_bytes())
    assert np.array_equal(
        out.vertices[0], posed(body_service, subject, np.array([1.0]))[0].astype(np.float32)
    )
    assert np.allclose(fit.shape, subject.shape, atol=1e-6) and fit.report["distances"]["mean"] < 0.5
    assert np.allclose(upgraded.shape, subject.shape, atol=1e-6)
    assert np.allclose(upgraded.scales, subject_scales(body_service, subject), atol=1e-6)


def test_grpc_refuses_unusable_subjects_with_invalid_argument(target: str, subject: Subject) -> None:
    broken = dict(damaged(subject.to_bytes()))["truncated"]
    with grpc.insecure_channel(target) as channel:
        stub = pb_grpc.BodyfitStub(channel)
        with pytest.raises(grpc.RpcError) as caught:
            stub.Synthesize(pb.SynthesizeRequest(subject=broken), timeout=30)
        assert caught.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert dict(caught.value.trailing_metadata() or ())["bodyfit-field"] == "subject"
        request = pb.FitScanRequest(data=_points_npz(np.zeros((10, 3))), format="npz", subject=broken)
        with pytest.raises(grpc.RpcError) as caught:
            list(stub.FitScan(request, timeout=30))
        assert (
            caught.value.code() == grpc.StatusCode.INVALID_ARGUMENT
            and "bodyfit rig" in caught.value.details()
        )
    with GrpcClient(target, retries=0) as sdk, pytest.raises(InvalidRequestError, match="drop sex"):
        sdk.synthesize(coordinates={"knee_angle_r": [0.1]}, subject=subject, measurements=None, sex="male")


def test_grpc_builds_a_subject(target: str, body_service: BodyService) -> None:
    """BuildSubject from three registered meshes of one body, through the gRPC SDK: progress, then the
    report (the rig fits the scans within 2 mm; the joints the poses did not move are listed) and a subject
    file that loads against the model."""
    shape = np.random.default_rng(3).normal(size=(1, body_service.model.n_shape)) * 0.5
    bend = np.linspace(0.1, 0.3, 3)
    q = {"elbow_flex_r": bend, "knee_angle_l": bend, "arm_flex_l": bend}
    verts = body_service.synthesize(SynthRequest(shape=np.repeat(shape, 3, 0), coordinates=q)).vertices
    with GrpcClient(target, retries=0) as sdk:
        events: list[dict[str, Any]] = []
        built = sdk.build_subject(list(verts), progress=events.append, allow_undetermined=True)
    assert built.scans == ("scan0.npz", "scan1.npz", "scan2.npz") and events
    assert max(built.personal_mm) < 2.0 and "hip_r" in built.undetermined_joints
    loaded = Subject.from_bytes(built.subject, body_service.model)
    assert loaded.scans == built.scans and loaded.offsets.shape == (body_service.model.n_vertices, 3)

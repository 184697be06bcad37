"""Scan hints and the frame convention over REST and gRPC: the hints travel as form fields and request
fields, come back in the report with how each was used, and a bad one is refused before any upload is read
(422 / INVALID_ARGUMENT naming the hint and its allowed values); ``to_model`` travels with the arrays and the
registration lies on the input as it was sent."""

from __future__ import annotations

import io
from collections.abc import Iterator
from typing import Any

import grpc
import numpy as np
import pytest
import trimesh
from fastapi.testclient import TestClient

from bodyfit.api import bodyfit_pb2 as pb
from bodyfit.api import bodyfit_pb2_grpc as pb_grpc
from bodyfit.api.grpc_server import create_grpc_server
from bodyfit.api.rest.app import create_app
from bodyfit.api.settings import ServiceSettings
from bodyfit.clients.grpc_client import GrpcClient
from bodyfit.clients.results import decode_array
from bodyfit.models.fitting.common.surface import point_to_surface
from bodyfit.models.fitting.registered.smpl_topology import SMPL_TO_BODY, SOURCE_DIR, read_obj
from bodyfit.service.core import BodyService, SynthRequest

BAD_HINTS = [
    ({"up": "north"}, "up", "up must be one of +x, -x, +y, -y, +z, -z"),
    ({"up": "+y", "facing": "+y"}, "facing", "perpendicular to up"),
    ({"pose": "kneeling"}, "pose", "pose must be one of standing, sitting, a-pose, t-pose"),
    ({"sex": "x"}, "sex", "sex must be one of male, female, neutral"),
    ({"height_m": 17.5}, "height_m", "between 1.2 and 2.3"),
]


@pytest.fixture(scope="module")
def rest(body_service: BodyService) -> Iterator[TestClient]:
    with TestClient(create_app(ServiceSettings(), service=body_service), raise_server_exceptions=False) as c:
        yield c


@pytest.fixture(scope="module")
def target(body_service: BodyService) -> Iterator[str]:
    server, port = create_grpc_server(body_service, "127.0.0.1:0", ServiceSettings(max_upload_mb=4.0))
    server.start()
    yield f"127.0.0.1:{port}"
    server.stop(grace=1).wait()


def _npz(points: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, points=points)
    return buf.getvalue()


@pytest.mark.parametrize(("hints", "field", "words"), BAD_HINTS)
def test_rest_refuses_a_bad_hint_naming_its_allowed_values(
    rest: TestClient, hints: dict[str, Any], field: str, words: str
) -> None:
    files = {"file": ("scan.npz", b"not read: the hints are checked first")}
    r = rest.post("/v1/fit/scan", files=files, data={k: str(v) for k, v in hints.items()})
    assert r.status_code == 422 and r.headers["content-type"].startswith("application/problem+json")
    problem = r.json()
    assert problem["field"] == field and words in problem["detail"], problem


@pytest.mark.parametrize(("hints", "field", "words"), BAD_HINTS)
def test_grpc_refuses_a_bad_hint_naming_its_allowed_values(
    target: str, hints: dict[str, Any], field: str, words: str
) -> None:
    request = pb.FitScanRequest(data=b"not read", format="npz", **hints)
    with grpc.insecure_channel(target) as channel, pytest.raises(grpc.RpcError) as err:
        list(pb_grpc.BodyfitStub(channel).FitScan(request, timeout=30))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and words in err.value.details()
    assert dict(err.value.trailing_metadata())["bodyfit-field"] == field


def test_rest_reports_the_hints_and_answers_in_the_inputs_frame(
    rest: TestClient, body_service: BodyService
) -> None:
    """A registered mesh turned and moved: placed by its own vertices, it records up, facing and the pose
    class without using them, checks the height, and its registration lies on the upload."""
    body = body_service.synthesize(SynthRequest(coordinates={"knee_angle_r": 0.5})).vertices[0]
    moved = body @ np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]).T + [0.5, 0.1, -2.0]
    fields = {"up": "y", "facing": "-z", "pose": "T-pose", "sex": "male", "height_m": "1.75"}
    r = rest.post("/v1/fit/scan", files={"file": ("mesh.npz", _npz(moved))}, data=fields)
    assert r.status_code == 200, r.text
    doc = r.json()
    hints = doc["report"]["extra"]["hints"]
    assert {k: h["value"] for k, h in hints.items()} == {
        "up": "+y",
        "facing": "-z",
        "pose": "t-pose",
        "sex": "male",
        "height_m": 1.75,
    }
    assert [k for k, h in hints.items() if h["used"]] == ["height_m"]
    vertices = decode_array(doc["arrays"]["vertices"])
    assert np.linalg.norm(vertices - moved, axis=1).mean() < 0.003
    np.testing.assert_array_equal(decode_array(doc["arrays"]["to_model"]), np.eye(4, dtype=np.float32))


def test_grpc_fits_a_turned_smpl_mesh_in_its_own_frame_from_its_hints(target: str) -> None:
    """The CC BY man turned to +Z up and facing +X: with up and facing given over gRPC the registration lies
    on the mesh as it was sent, and to_model is the hinted turn into the model's frame."""
    verts, faces = read_obj(SOURCE_DIR / "human_man.obj")
    axes = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # SMPL's +Y -> +Z, +Z -> +X
    moved = verts @ axes.T + np.array([0.2, -0.5, 1.0])
    data = trimesh.Trimesh(moved, faces, process=False).export(file_type="ply")
    assert isinstance(data, bytes)
    with GrpcClient(target, retries=0) as client:
        fit = client.fit_scan(data, format="ply", up="+z", facing="+x", pose="t-pose")
    assert fit.fitted_as == "SMPL topology" and fit.report["predicted_error_mm"] is not None
    assert point_to_surface(fit.vertices.astype(np.float64), moved, faces).mean() < 0.005
    assert fit.to_model is not None
    np.testing.assert_allclose(fit.to_model[:3, :3], SMPL_TO_BODY @ axes.T, atol=1e-6)
    hints = fit.report["extra"]["hints"]
    assert hints["up"]["used"] and hints["facing"]["used"] and not hints["pose"]["used"]
    assert fit.report["scan_to_model"]["max"] >= fit.report["distances"]["max"]

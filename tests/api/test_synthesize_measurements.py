"""Bodies built from measurements in ``/v1/synthesize``: over REST, gRPC, the SDK and the CLI the body is
the one :func:`shape_from_measurements` builds, its requested and achieved measurements come back with it,
and unknown names, implausible values and contradictory fields are refused naming the field."""

from __future__ import annotations

import io
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from bodyfit.api import bodyfit_pb2 as pb
from bodyfit.api.grpc_server import create_grpc_server
from bodyfit.api.rest.app import create_app
from bodyfit.api.rest.routes_synth import BUILT_HEADER
from bodyfit.api.settings import ServiceSettings
from bodyfit.cli import app as cli
from bodyfit.clients.errors import InvalidRequestError
from bodyfit.clients.grpc_client import GrpcClient
from bodyfit.clients.rest_client import Client
from bodyfit.models.anthropometry.inverse import shape_from_measurements
from bodyfit.service.core import BodyService, SynthRequest
from bodyfit.service.errors import InvalidInputError
from bodyfit.wire.measure import Measurements

ASKED = {"stature": 1.80, "mass": 82.0, "waist": 0.88}


@pytest.fixture(scope="module")
def app(body_service: BodyService) -> Any:
    return create_app(service=body_service)


@pytest.fixture(scope="module")
def rest(app: Any) -> Iterator[TestClient]:
    with TestClient(app) as c:
        yield c


@pytest.fixture(scope="module")
def grpc_target(body_service: BodyService) -> Iterator[str]:
    server, port = create_grpc_server(body_service, "127.0.0.1:0", ServiceSettings())
    server.start()
    yield f"127.0.0.1:{port}"
    server.stop(grace=1).wait()


@pytest.fixture(scope="module")
def expected(body_service: BodyService) -> Any:
    return shape_from_measurements(body_service.model, ASKED, sex="male")


def test_the_core_builds_every_body_of_the_batch_from_the_measurements(
    body_service: BodyService, expected: Any
) -> None:
    request, built = body_service.with_built_shape(
        SynthRequest(coordinates={"knee_angle_r": [0.0, 1.0]}, measurements=ASKED, sex="male")
    )
    assert built is not None and request.measurements is None and request.shape is not None
    assert request.shape.shape == (2, 32)
    np.testing.assert_allclose(request.shape, np.repeat(expected.shape[None], 2, 0), atol=1e-12)
    assert built.requested == {"stature": 1.8, "weightkg": 82.0, "waistcircumference": 0.88}
    assert built.values["stature"][0] == pytest.approx(expected.achieved["stature"])
    # synthesize() builds too: the same vertices as the built shape given directly
    direct = body_service.synthesize(SynthRequest(shape=expected.shape[None]))
    from_measurements = body_service.synthesize(SynthRequest(measurements=ASKED, sex="male"))
    np.testing.assert_allclose(from_measurements.vertices, direct.vertices, atol=1e-6)
    plain, none = body_service.with_built_shape(SynthRequest(batch=2))
    assert none is None and plain == SynthRequest(batch=2)


@pytest.mark.parametrize(
    ("request_", "field", "words"),
    [
        (SynthRequest(shape=np.zeros((1, 32)), measurements=ASKED), "measurements", "not both"),
        (SynthRequest(sex="male"), "sex", "sex goes with measurements"),
        (SynthRequest(measurements={"statur": 1.8}), "measurements", "did you mean 'stature'"),
        (SynthRequest(measurements={"waist": 3.0}), "measurements", "is not plausible"),
        (SynthRequest(measurements={"stature": 1.7}, sex="other"), "measurements", "sex must be"),
    ],
)
def test_the_core_refuses_naming_the_field(
    body_service: BodyService, request_: SynthRequest, field: str, words: str
) -> None:
    with pytest.raises(InvalidInputError, match=words) as info:
        body_service.with_built_shape(request_)
    assert info.value.field == field


def test_rest_answers_the_body_and_its_measurements(rest: TestClient, expected: Any) -> None:
    response = rest.post("/v1/synthesize", json={"measurements": ASKED, "sex": "male", "batch": 2})
    assert response.status_code == 200, response.text
    with np.load(io.BytesIO(response.content)) as npz:
        assert npz["vertices"].shape[0] == 2
        stature = npz["vertices"][0, :, 1].max() - npz["vertices"][0, :, 1].min()
    built = Measurements.model_validate_json(response.headers[BUILT_HEADER])
    assert len(response.headers[BUILT_HEADER]) < 4096
    assert built.requested is not None and built.requested["stature"] == 1.8
    assert built.residuals is not None and abs(built.residuals["stature"]) < 0.005
    assert built.shape == [expected.shape.tolist()]
    assert stature == pytest.approx(1.8, abs=0.03)  # the mesh's extent is the stature, near enough
    plain = rest.post("/v1/synthesize", json={"batch": 1})
    assert BUILT_HEADER not in plain.headers


@pytest.mark.parametrize(
    ("body", "words"),
    [
        ({"measurements": {"waist": 3.0}}, "waistcircumference = 3 m is not plausible"),
        ({"measurements": {"wasit": 0.9}, "sex": "male"}, "did you mean"),
        ({"measurements": ASKED, "shape": [[0.0] * 32]}, "not both"),
        ({"sex": "female"}, "sex goes with measurements"),
        ({"measurements": {"stature": "tall"}}, "valid number"),
    ],
)
def test_rest_refusals_name_the_measurement(rest: TestClient, body: dict[str, Any], words: str) -> None:
    response = rest.post("/v1/synthesize", json=body)
    assert response.status_code == 422, response.status_code
    assert words in response.text


def test_the_sdk_over_rest_and_grpc_builds_the_same_body(app: Any, grpc_target: str, expected: Any) -> None:
    with Client("http://testserver", http_client=TestClient(app)) as c:
        over_rest = c.synthesize(measurements=ASKED, sex="male")
        glb = c.synthesize_file("glb", measurements=ASKED, sex="male")
        with pytest.raises(InvalidRequestError, match="did you mean 'stature'"):
            c.synthesize(measurements={"statur": 1.8})
    with GrpcClient(grpc_target, retries=0) as g:
        over_grpc = g.synthesize(measurements=ASKED, sex="male")
        assert g.synthesize_file("glb", measurements=ASKED, sex="male") == glb
        assert g.synthesize(batch=1).built is None
        with pytest.raises(InvalidRequestError, match="is not plausible") as info:
            g.synthesize(measurements={"waist": 3.0})
        assert info.value.field == "measurements"
    np.testing.assert_array_equal(over_rest.vertices, over_grpc.vertices)
    assert over_rest.built is not None and over_rest.built == over_grpc.built
    assert over_rest.built.shape == [expected.shape.tolist()]
    assert set(over_rest.built.values) == set(expected.achieved)
    with pytest.raises(ValueError, match="not both"):
        Client("http://unused").synthesize(shape=np.zeros((1, 32)), measurements=ASKED)


def test_grpc_answers_the_build_beside_the_arrays(grpc_target: str) -> None:
    import grpc

    from bodyfit.api import bodyfit_pb2_grpc as pb_grpc

    with grpc.insecure_channel(grpc_target) as channel:
        stub = pb_grpc.BodyfitStub(channel)
        answer = stub.Synthesize(
            pb.SynthesizeRequest(measurements={"stature": 1.6}, sex="female"), timeout=30
        )
        assert answer.built.requested["stature"] == 1.6 and answer.vertices.shape[0] == 1
        assert abs(answer.built.residuals["stature"]) < 0.005 and not answer.built.flagged
        plain = stub.Synthesize(pb.SynthesizeRequest(batch=1), timeout=30)
        assert not plain.HasField("built")


def test_the_command_line_builds_and_reports_locally_and_from_a_server(
    app: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, expected: Any
) -> None:
    import bodyfit.clients.rest_client as rest_module

    args = ["-m", "stature=1.80", "-m", "mass=82", "-m", "waist=0.88", "--sex", "male"]
    local = CliRunner().invoke(cli, ["synth", str(tmp_path / "local.npz"), *args])
    assert local.exit_code == 0, local.output
    assert "stature: asked   1800.0 mm, built" in local.stdout
    assert "weightkg: asked     82.0 kg" in local.stdout
    monkeypatch.setattr(rest_module, "Client", lambda url: Client(url, http_client=TestClient(app)))
    served = CliRunner().invoke(cli, ["synth", str(tmp_path / "served.npz"), *args, "--server", "http://b"])
    assert served.exit_code == 0, served.output
    assert served.stdout.splitlines()[1:] == local.stdout.splitlines()[1:]
    with np.load(tmp_path / "local.npz") as a, np.load(tmp_path / "served.npz") as b:
        np.testing.assert_allclose(a["vertices"], b["vertices"], atol=1e-5)
    both = CliRunner().invoke(cli, ["synth", str(tmp_path / "x.npz"), "--shape", "0", "-m", "stature=1.8"])
    assert both.exit_code == 2 and "not both" in both.output
    unknown = CliRunner().invoke(cli, ["synth", str(tmp_path / "x.npz"), "-m", "statur=1.8"])
    assert unknown.exit_code == 2 and "did you mean 'stature'" in unknown.output
    assert json.loads(json.dumps(expected.residuals))  # the residuals are plain floats

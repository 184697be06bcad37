"""POST /v1/measure: parameters, a mesh in our topology, or measurements in; measurements out, the same as
the model-level functions give; bad names and implausible values refused with a problem naming them."""

from __future__ import annotations

import io
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import torch
from fastapi.testclient import TestClient

from bodyfit.api.rest.app import create_app
from bodyfit.models.anthropometry.measure import body_in_pose, measure
from bodyfit.service.core import BodyService
from bodyfit.wire.measure import Measurements


@pytest.fixture(scope="module")
def client(body_service: BodyService) -> Iterator[TestClient]:
    with TestClient(create_app(service=body_service)) as c:
        yield c


def _problem(response: Any) -> dict[str, Any]:
    assert response.status_code == 422, response.text
    assert response.headers["content-type"].startswith("application/problem+json")
    doc: dict[str, Any] = response.json()
    return doc


def test_parameters_in_give_the_model_level_measurements(
    client: TestClient, body_service: BodyService
) -> None:
    shape = np.zeros((2, body_service.model.n_shape))
    shape[1, 0] = 1.5  # a larger skeleton
    response = client.post("/v1/measure", json={"shape": shape.tolist()})
    assert response.status_code == 200, response.text
    answer = Measurements.model_validate_json(response.content)
    expected = measure(body_service.model, shape)
    assert list(answer.values) == list(expected)
    np.testing.assert_allclose(answer.values["stature"], expected["stature"], atol=1e-5)
    np.testing.assert_allclose(answer.values["weightkg"], expected["weightkg"], rtol=1e-5)
    assert answer.values["stature"][1] > answer.values["stature"][0] + 0.02
    units = {m.name: m.unit for m in answer.measurements}
    assert units["stature"] == "m" and units["weightkg"] == "kg"
    assert answer.shape is None and not answer.flagged


def test_named_coordinates_pose_the_body_before_measuring(
    client: TestClient, body_service: BodyService
) -> None:
    model = body_service.model
    names = {"hip_flexion_r": 1.2, "knee_angle_r": 1.5}
    shape = [[0.0] * 32]
    standing = client.post("/v1/measure", json={"shape": shape}).json()["values"]
    bent = client.post("/v1/measure", json={"shape": shape, "coordinates": names})
    assert bent.status_code == 200, bent.text
    values = bent.json()["values"]
    q = model.skeleton.coordinates({k: np.asarray(v) for k, v in names.items()}, batch=1)
    expected = measure(model, np.zeros((1, 32)), q)
    assert values["kneeheightmidpatella"][0] == pytest.approx(expected["kneeheightmidpatella"][0], abs=1e-5)
    # the coordinates replace the measuring posture: the right thigh comes up
    assert values["kneeheightmidpatella"][0] > standing["kneeheightmidpatella"][0] + 0.1


def test_a_mesh_in_our_topology_is_measured_as_its_parameters(
    client: TestClient, body_service: BodyService
) -> None:
    model = body_service.model
    shape = np.zeros((1, model.n_shape))
    shape[0, 9] = 1.0
    vertices, _ = body_in_pose(model, torch.as_tensor(shape, dtype=torch.float32))
    buf = io.BytesIO()
    np.savez(buf, vertices=vertices[0].numpy())
    response = client.post("/v1/measure", files={"file": ("body.npz", buf.getvalue())})
    assert response.status_code == 200, response.text
    values = response.json()["values"]
    expected = measure(model, shape)
    assert values["stature"][0] == pytest.approx(expected["stature"][0], abs=1e-4)
    # the mesh's joints are regressed from its vertices: the limb lengths agree within about 2 cm
    assert values["weightkg"][0] == pytest.approx(expected["weightkg"][0], rel=1e-3)


def test_measurements_in_give_a_body_that_meets_them(client: TestClient) -> None:
    asked = {"stature": 1.82, "mass": 84.0, "waist": 0.92}
    response = client.post("/v1/measure", json={"measurements": asked, "sex": "male"})
    assert response.status_code == 200, response.text
    answer = Measurements.model_validate_json(response.content)
    assert answer.shape is not None and len(answer.shape[0]) == 32
    assert answer.residuals is not None
    assert set(answer.residuals) == {"stature", "weightkg", "waistcircumference"}
    assert abs(answer.residuals["stature"]) < 0.005 and abs(answer.residuals["weightkg"]) < 1.0
    assert abs(answer.residuals["waistcircumference"]) < 0.008
    assert answer.values["stature"][0] == pytest.approx(1.82, abs=0.005)
    assert not answer.flagged and answer.unmet == []


def test_an_unknown_name_is_refused_with_suggestions(client: TestClient) -> None:
    doc = _problem(client.post("/v1/measure", json={"measurements": {"statur": 1.8}}))
    assert "'statur'" in doc["detail"] and "did you mean 'stature'" in doc["detail"]
    assert doc["field"] == "measurements"


def test_an_implausible_value_is_refused_naming_it_and_its_range(client: TestClient) -> None:
    doc = _problem(client.post("/v1/measure", json={"measurements": {"waist": 3.0}, "sex": "female"}))
    assert "waistcircumference = 3 m" in doc["detail"] and "expected" in doc["detail"]
    doc = _problem(client.post("/v1/measure", json={"measurements": {"stature": 1.6, "crotchheight": 1.0}}))
    assert "crotchheight = 1 m contradicts the stature 1.6 m" in doc["detail"]


@pytest.mark.parametrize(
    "body, words",
    [
        ({"shape": [[0.0] * 5]}, "(1, 32)"),
        ({}, "either shape"),
        ({"shape": [[0.0] * 32], "measurements": {"stature": 1.8}}, "either shape"),
        ({"measurements": {"stature": 1.8}, "sex": "other"}, "sex"),
        ({"shape": [[0.0] * 32], "coordinates": {"no_such_dof": 0.1}}, "no_such_dof"),
    ],
)
def test_malformed_requests_are_refused(client: TestClient, body: dict[str, Any], words: str) -> None:
    assert words in _problem(client.post("/v1/measure", json=body))["detail"]


def test_a_mesh_of_another_vertex_count_is_refused(client: TestClient) -> None:
    buf = io.BytesIO()
    rng = np.random.default_rng(0)
    np.savez(buf, vertices=rng.normal(size=(500, 3)) * [0.2, 0.5, 0.1] + [0, 0.9, 0])
    doc = _problem(client.post("/v1/measure", files={"file": ("cloud.npz", buf.getvalue())}))
    assert "13348" in doc["detail"]


def test_the_endpoint_is_published_with_both_request_bodies(client: TestClient) -> None:
    spec = client.get("/openapi.json").json()
    op = spec["paths"]["/v1/measure"]["post"]
    assert set(op["requestBody"]["content"]) == {"application/json", "multipart/form-data"}
    assert op["responses"]["200"]["content"]["application/json"]["schema"]["$ref"].endswith("/Measurements")

"""``Client.measure`` and ``AsyncClient.measure`` against the REST app served in process: parameters, a mesh
and measurements in, the server's measurements read through :mod:`bodyfit.wire.measure`; refusals raised as
typed errors; the gRPC client answers the same."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import torch
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from bodyfit.api.grpc_server import create_grpc_server
from bodyfit.api.rest.app import create_app
from bodyfit.api.settings import ServiceSettings
from bodyfit.cli import app as cli
from bodyfit.clients.errors import InvalidRequestError
from bodyfit.clients.grpc_client import GrpcClient
from bodyfit.clients.rest_client import AsyncClient, Client
from bodyfit.models.anthropometry.measure import body_in_pose, measure
from bodyfit.service.core import BodyService
from bodyfit.wire.measure import Measurements


@pytest.fixture(scope="module")
def app(body_service: BodyService) -> Any:
    return create_app(service=body_service)


@pytest.fixture(scope="module")
def client(app: Any) -> Iterator[Client]:
    with Client("http://testserver", http_client=TestClient(app)) as c:
        yield c


def test_parameters_and_a_mesh_are_measured_as_the_model_measures_them(
    client: Client, body_service: BodyService
) -> None:
    model = body_service.model
    shape = np.zeros((2, model.n_shape))
    shape[1, 0] = -1.0
    expected = measure(model, shape)
    answer = client.measure(shape=shape)
    assert isinstance(answer, Measurements)
    np.testing.assert_allclose(answer.values["stature"], expected["stature"], atol=1e-5)
    vertices, _ = body_in_pose(model, torch.as_tensor(shape[1:], dtype=torch.float32))
    from_mesh = client.measure(mesh=vertices[0].numpy())
    assert from_mesh.values["stature"][0] == pytest.approx(expected["stature"][1], abs=1e-4)
    posed = client.measure(shape=shape[:1], coordinates={"hip_flexion_r": 1.0})
    assert posed.values["stature"] == pytest.approx(expected["stature"][:1], abs=1e-4)  # the head stays


def test_measurements_build_a_body_sync_and_async_alike(client: Client, app: Any) -> None:
    asked = {"stature": 1.65, "mass": 62.0}
    built = client.measure(measurements=asked, sex="female")
    assert built.shape is not None and built.residuals is not None
    assert abs(built.residuals["stature"]) < 0.005 and abs(built.residuals["weightkg"]) < 1.0

    async def run() -> Measurements:
        http = httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://testserver")
        async with AsyncClient(http_client=http) as c:
            return await c.measure(measurements=asked, sex="female")

    assert asyncio.run(run()) == built


def test_refusals_are_typed_errors_naming_the_measurement(client: Client) -> None:
    with pytest.raises(InvalidRequestError, match="did you mean 'stature'"):
        client.measure(measurements={"statur": 1.8})
    with pytest.raises(InvalidRequestError, match=r"waistcircumference = 2\.5 m is not plausible"):
        client.measure(measurements={"waist": 2.5})
    with pytest.raises(ValueError, match="exactly one of shape, mesh and measurements"):
        client.measure(shape=np.zeros(32), measurements={"stature": 1.8})


def test_the_grpc_client_measures_as_the_rest_client(client: Client, body_service: BodyService) -> None:
    server, port = create_grpc_server(body_service, "127.0.0.1:0", ServiceSettings())
    server.start()
    try:
        with GrpcClient(f"127.0.0.1:{port}", retries=0) as g:
            shape = np.zeros((2, 32))
            shape[1, 3] = 1.0
            assert g.measure(shape=shape) == client.measure(shape=shape)
            posed = {"hip_flexion_r": [0.5, 1.0]}
            assert g.measure(shape=shape, coordinates=posed) == client.measure(shape=shape, coordinates=posed)
            vertices, _ = body_in_pose(body_service.model, torch.zeros(1, 32))
            mesh = vertices[0].numpy()
            assert g.measure(mesh=mesh) == client.measure(mesh=mesh)
            asked = {"stature": 1.9, "mass": 95.0, "waist": 0.95}
            built = g.measure(measurements=asked, sex="male")
            assert built == client.measure(measurements=asked, sex="male")
            assert built.requested == {"stature": 1.9, "weightkg": 95.0, "waistcircumference": 0.95}
            with pytest.raises(InvalidRequestError, match="did you mean 'stature'") as info:
                g.measure(measurements={"statur": 1.8})
            assert info.value.field == "measurements"
    finally:
        server.stop(grace=1).wait()


def test_the_command_line_asks_a_server(
    app: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, body_service: BodyService
) -> None:
    import bodyfit.clients.rest_client as rest

    urls: list[str] = []

    def served(url: str) -> Client:  # the server at ``url`` is the app in this process
        urls.append(url)
        return Client(url, http_client=TestClient(app))

    monkeypatch.setattr(rest, "Client", served)
    path = tmp_path / "fit.npz"
    np.savez(path, shape=np.zeros((1, 32)))
    result = CliRunner().invoke(cli, ["measure", str(path), "--json", "--server", "http://body:8000"])
    assert result.exit_code == 0, result.output
    stature = json.loads(result.stdout)["measurements"]["stature"]
    assert urls == ["http://body:8000"]
    assert stature == pytest.approx(measure(body_service.model, np.zeros(32))["stature"], abs=1e-5)
    out = tmp_path / "body.npz"
    args = ["measure", "-s", "stature=1.7", "--server", "http://body:8000", "--out", str(out)]
    table = CliRunner().invoke(cli, args)
    assert table.exit_code == 0, table.output
    assert "(asked 1700.0 mm)" in table.stdout and np.load(out)["shape"].shape == (1, 32)
    refused = CliRunner().invoke(cli, ["measure", "-s", "statur=1.7", "--server", "http://body:8000"])
    assert refused.exit_code == 2 and "did you mean 'stature'" in refused.output

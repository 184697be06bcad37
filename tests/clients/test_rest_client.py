"""The REST SDK against the in-process app: numpy in and out, typed errors, progress, retries."""

from __future__ import annotations

import asyncio
import io
from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from bodyfit.api.rest.app import create_app
from bodyfit.clients.errors import (
    ConnectionFailedError,
    InvalidRequestError,
    RequestTooLargeError,
    ServerBusyError,
)
from bodyfit.clients.rest_client import AsyncClient, Client
from bodyfit.service.core import BodyService


@pytest.fixture(scope="module")
def app(body_service: BodyService) -> Any:
    return create_app(service=body_service)


@pytest.fixture(scope="module")
def client(app: Any) -> Iterator[Client]:
    with Client("http://testserver", http_client=TestClient(app)) as c:
        yield c


def test_model_info_and_synthesis(client: Client) -> None:
    info = client.model_info()
    assert info.n_shape == 32 and info.dof_ranges.shape == (46, 2) and "knee_angle_r" in info.dof_names
    shape = np.zeros((2, info.n_shape))
    shape[1, 0] = 2.0  # a larger skeleton
    out = client.synthesize(shape=shape, coordinates={"knee_angle_r": 0.3}, skeleton=True, faces=True)
    assert out.vertices.shape == (2, 13348, 3) and out.vertices.dtype == np.float32
    assert out.faces is not None and out.bones is not None and out.bone_faces is not None
    height = out.vertices[:, :, 1].max(1) - out.vertices[:, :, 1].min(1)
    assert abs(height[1] - height[0]) > 0.01
    ply = client.synthesize_file("ply", coordinates={"knee_angle_r": 0.3})
    assert ply.startswith(b"ply")


def test_typed_errors(client: Client) -> None:
    with pytest.raises(InvalidRequestError) as err:
        client.synthesize(coordinates={"knee_angle_r": 7.0})
    assert err.value.field == "coordinates" and err.value.status == 422 and "range" in err.value.detail
    with pytest.raises(RequestTooLargeError):
        client.synthesize(batch=10_000)


def test_fit_scan_and_sequence_with_progress(client: Client) -> None:
    target = client.synthesize(coordinates={"arm_flex_r": 0.6})
    buf = io.BytesIO()
    np.savez(buf, points=target.vertices[0])
    events: list[dict[str, Any]] = []
    fit = client.fit_scan(buf.getvalue(), format="npz", progress=events.append)
    assert fit.fitted_as == "registered" and fit.confident and fit.report["distances"]["mean"] < 2.0
    assert fit.coordinates.shape == (46,) and fit.dof_names[0] == "pelvis_tilt" and events
    frames = client.synthesize(coordinates={"knee_angle_r": np.linspace(0.0, 0.9, 5)}).vertices
    seq = client.fit_sequence(frames, chunk=2)
    assert seq.coordinates.shape == (5, 46) and seq.vertices.shape == (5, 13348, 3)
    knee = seq.dof_names.index("knee_angle_r")
    assert np.abs(seq.coordinates[:, knee] - np.linspace(0.0, 0.9, 5)).max() < 0.1
    assert seq.error_mm.shape == (5,) and seq.error_mm.max() < 3.0 and seq.limit_violations == 0


def test_fit_scan_takes_points_and_says_what_it_cannot_send(client: Client) -> None:
    """An (N, 3) array goes as an .npz of points; a wrong shape, a format other than npz with an array, and
    an object that is no scan are refused before anything is sent."""
    target = client.synthesize(coordinates={"arm_flex_r": 0.6})
    fit = client.fit_scan(target.vertices[0])
    assert fit.fitted_as == "registered" and fit.report["distances"]["mean"] < 2.0
    with pytest.raises(ValueError, match=r"\(N, 3\) array; got shape \(13348, 2\)"):
        client.fit_scan(target.vertices[0][:, :2])
    with pytest.raises(ValueError, match="sent as npz"):
        client.fit_scan(target.vertices[0], format="ply")
    with pytest.raises(TypeError, match="file path, bytes with format=, or an \\(N, 3\\) array"):
        client.fit_scan(target.vertices[0].tolist())


def test_input_errors_found_by_the_fit_are_invalid_request_errors(
    client: Client, body_service: BodyService, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The SDK streams fits: a scan read in the wrong units (refused before the stream) and a model-layer
    input error raised by the fit itself (an NDJSON error event) both raise InvalidRequestError, not
    ServerError."""
    from bodyfit.io.scans import ScanError

    points = np.random.default_rng(0).uniform([-0.2, 0.0, -0.15], [0.2, 1.7, 0.15], (2000, 3))
    with pytest.raises(InvalidRequestError, match="units=mm") as bad:
        client.fit_scan(points, units="mm")
    assert bad.value.status == 422 and bad.value.field == "units"

    def fit_mesh(*args: object, **kwargs: object) -> None:
        raise ScanError("only 4 points are left after thinning to a 1 cm grid")

    monkeypatch.setattr(body_service, "fit_mesh", fit_mesh)
    with pytest.raises(InvalidRequestError, match="only 4 points") as err:
        client.fit_scan(points)
    assert err.value.status == 422
    with pytest.raises(InvalidRequestError, match="0 bodies"):
        client.synthesize_file("glb", shape=np.zeros((0, 32)))


def test_async_client(app: Any) -> None:
    async def run() -> tuple[int, np.ndarray]:
        transport = httpx.ASGITransport(app=app)
        async with AsyncClient(http_client=httpx.AsyncClient(transport=transport, base_url="http://t")) as c:
            info = await c.model_info()
            out = await c.synthesize(batch=3)
            with pytest.raises(InvalidRequestError):
                await c.synthesize(shape=np.zeros((1, 3)))
            return info.n_vertices, out.vertices

    n, vertices = asyncio.run(run())
    assert n == 13348 and vertices.shape == (3, 13348, 3)


def test_retries_only_idempotent_calls_when_busy() -> None:
    calls: list[str] = []

    def handler(request: httpx.Request) -> httpx.Response:
        calls.append(request.url.path)
        problem = {"kind": "unavailable", "detail": "loading", "status": 503}
        return httpx.Response(503, json=problem, headers={"content-type": "application/problem+json"})

    http = httpx.Client(transport=httpx.MockTransport(handler), base_url="http://t")
    client = Client(http_client=http, retries=2)
    with pytest.raises(ServerBusyError, match="loading"):
        client.model_info()
    assert calls == ["/v1/model"] * 3
    calls.clear()
    with pytest.raises(ServerBusyError):
        client.fit_scan(b"ply", format="ply")
    assert calls == ["/v1/fit/scan"]


def test_unreachable_server() -> None:
    with (
        Client("http://127.0.0.1:9", retries=0, timeout=2.0) as client,
        pytest.raises(ConnectionFailedError, match="cannot reach"),
    ):
        client.model_info()

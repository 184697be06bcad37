"""The wire models (bodyfit.wire) against the real server: every event and answer the REST flows emit reads
back into its model and writes out to the same JSON, nothing the models leave undeclared; a malformed
answer is a ServerError in the SDK that says where; the OpenAPI document lists the models."""

from __future__ import annotations

import dataclasses
import io
import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from pydantic import BaseModel

from bodyfit import wire as w
from bodyfit.api.rest.app import create_app
from bodyfit.api.settings import ServiceSettings
from bodyfit.clients.errors import ServerError
from bodyfit.clients.rest_client import Client
from bodyfit.service.core import BodyService, SynthRequest
from bodyfit.service.formats import json_bytes

SEQUENCE = Path(__file__).resolve().parents[1] / "data" / "smpl_format" / "cmu_131_smpl.npz"
NDJSON = {"accept": "application/x-ndjson"}


@pytest.fixture(scope="module")
def client(body_service: BodyService) -> Iterator[TestClient]:
    app = create_app(ServiceSettings(max_upload_mb=2.0), service=body_service)
    with TestClient(app, raise_server_exceptions=False) as c:
        yield c


def npz(**arrays: Any) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def reads_back(doc: dict[str, Any], read: Callable[[Any], BaseModel]) -> BaseModel:
    """``doc`` read into its model, which writes it out again unchanged (NaN as null, as the server does):
    a key the model does not declare would be left out (but by the open documents: a fit's report, a
    sequence's statistics, an upgrade's summary)."""
    model = read(doc)
    assert json.loads(json_bytes(model.model_dump(mode="json"))) == doc
    return model


def stream(client: TestClient, path: str, **kwargs: Any) -> list[dict[str, Any]]:
    with client.stream("POST", path, headers=NDJSON, **kwargs) as r:
        assert r.status_code == 200, r.read()
        return [json.loads(line) for line in r.iter_lines() if line]


@pytest.fixture(scope="module")
def scan_file(body_service: BodyService) -> dict[str, Any]:
    verts = body_service.synthesize(SynthRequest(coordinates={"knee_angle_r": 0.8})).vertices[0]
    return {"file": ("body.npz", npz(points=verts))}


@pytest.fixture(scope="module")
def sequence_file(body_service: BodyService) -> dict[str, Any]:
    frames = body_service.synthesize(SynthRequest(coordinates={"knee_angle_l": np.linspace(0, 1, 5)}))
    return {"file": ("seq.npz", npz(frames=frames.vertices))}


def test_scan_fit_events_and_answer(client: TestClient, scan_file: dict[str, Any]) -> None:
    events = stream(client, "/v1/fit/scan", files=scan_file)
    read = w.SCAN_EVENTS.validate_python
    models = [reads_back(e, read) for e in events]
    assert [type(m) for m in models] == [w.ProgressEvent, w.ProgressEvent, w.MeshFitEvent]
    fit = models[-1]
    assert isinstance(fit, w.MeshFitEvent) and fit.fitted_as == "registered"
    assert fit.arrays.vertices.to_numpy().shape == (13348, 3) and fit.arrays.vertices.dtype == "float32"
    answer = client.post("/v1/fit/scan", files=scan_file).json()
    reads_back(answer, w.MeshFit.model_validate)
    assert "event" not in answer


def test_sequence_fit_events_and_answer(client: TestClient, sequence_file: dict[str, Any]) -> None:
    events = stream(client, "/v1/fit/sequence?chunk=2", files=sequence_file)
    models = [reads_back(e, w.SEQUENCE_EVENTS.validate_python) for e in events]
    chunks = [m for m in models if isinstance(m, w.SequenceChunkEvent)]
    assert [(c.start, c.stop) for c in chunks] == [(0, 2), (2, 4), (4, 5)]
    assert isinstance(models[-1], w.SequenceResultEvent) and models[-1].stats.frames == 5
    assert chunks[-1].arrays.vertices.to_numpy().shape == (1, 13348, 3)
    answer = client.post("/v1/fit/sequence?chunk=2", files=sequence_file).json()
    read = reads_back(answer, w.SequenceAnswer.model_validate)
    assert isinstance(read, w.SequenceAnswer) and len(read.chunks) == 3


@pytest.mark.parametrize("model_file", [True, False], ids=["path a", "path b"])
def test_upgrade_events_and_answer(client: TestClient, body_service: BodyService, model_file: bool) -> None:
    service = body_service if model_file else dataclasses.replace(body_service, _smpl=None)
    files = {"file": ("walk.npz", SEQUENCE.read_bytes())}
    with TestClient(create_app(service=service)) as c:
        events = stream(c, "/v1/upgrade?chunk=25", files=files)
        answer = c.post("/v1/upgrade?chunk=25", files=files).json()
    models = [reads_back(e, w.UPGRADE_EVENTS.validate_python) for e in events]
    result = models[-1]
    assert isinstance(result, w.UpgradeResultEvent) and set(result.files) == {"npz", "json", "osim", "mot"}
    assert result.summary.path == ("a" if model_file else "b")
    assert result.files["osim"].lstrip().startswith(b"<?xml")
    chunks = [(m.start, m.stop) for m in models if isinstance(m, w.UpgradeChunkEvent)]
    assert chunks == [(0, 25), (25, 50), (50, 60)]
    reads_back(answer, w.UpgradeAnswer.model_validate)


def test_an_error_midway_is_an_error_event(
    client: TestClient, body_service: BodyService, scan_file: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    from bodyfit.io.scans import ScanError

    def fit_mesh(*args: object, **kwargs: object) -> None:
        raise ScanError("only 4 points are left after thinning to a 1 cm grid")

    monkeypatch.setattr(body_service, "fit_mesh", fit_mesh)
    error = reads_back(stream(client, "/v1/fit/scan", files=scan_file)[-1], w.SCAN_EVENTS.validate_python)
    assert isinstance(error, w.ErrorEvent) and error.kind == "invalid_argument" and error.status == 422


def test_model_info_health_ready_and_problems(client: TestClient, body_service: BodyService) -> None:
    info = reads_back(client.get("/v1/model").json(), w.ModelInfo.model_validate)
    assert info == body_service.info()
    reads_back(client.get("/healthz").json(), w.Health.model_validate)
    reads_back(client.get("/readyz").json(), w.Ready.model_validate)
    refused = client.post("/v1/synthesize", json={"coordinates": {"knee_angle_r": 9.0}})
    problem = reads_back(refused.json(), w.Problem.model_validate)
    assert isinstance(problem, w.Problem) and problem.field == "coordinates" and problem.status == 422


def test_synthesis_as_json(client: TestClient) -> None:
    doc = client.post("/v1/synthesize", json={"format": "json", "faces": True, "skeleton": True}).json()
    body = w.SynthesisJSON.model_validate(doc)
    assert np.asarray(body.vertices).shape == (1, 13348, 3) and body.bones is not None and body.bone_faces


# -- the SDK reading malformed answers -------------------------------------------------------------------


def sdk_against(*lines: dict[str, Any]) -> Client:
    """A client whose server streams ``lines`` (NDJSON) for any request."""
    body = "".join(json.dumps(line) + "\n" for line in lines).encode()
    transport = httpx.MockTransport(lambda _: httpx.Response(200, content=body))
    return Client(http_client=httpx.Client(transport=transport, base_url="http://t"), retries=0)


def fit_event(client: TestClient, scan_file: dict[str, Any]) -> dict[str, Any]:
    return stream(client, "/v1/fit/scan", files=scan_file)[-1]


def test_a_malformed_result_is_a_server_error_saying_where(
    client: TestClient, scan_file: dict[str, Any]
) -> None:
    good = fit_event(client, scan_file)
    with sdk_against(good) as sdk:
        assert sdk.fit_scan(np.zeros((3, 3))).fitted_as == "registered"  # the server's own event reads
    missing = {**good, "arrays": {k: v for k, v in good["arrays"].items() if k != "vertices"}}
    short = {**good["arrays"]["root"], "shape": [4]}
    cases = [
        (missing, r"arrays\.vertices: Field required"),
        ({**good, "arrays": {**good["arrays"], "root": short}}, r"arrays\.root: .*holds 12 bytes.*need 16"),
        ({**good, "fitted_as": "guessed"}, r"fitted_as: Input should be 'registered'"),
        ({**good, "event": "finished"}, r"does not match any of the expected tags"),
        ({**good, "report": {**good["report"], "confident": "perhaps"}}, r"report\.confident"),
    ]
    for doc, where in cases:
        with sdk_against(doc) as sdk, pytest.raises(ServerError, match=where) as raised:
            sdk.fit_scan(np.zeros((3, 3)))
        assert "scan fit event does not match" in str(raised.value)


def test_a_malformed_model_info_or_stream_line_is_a_server_error() -> None:
    transport = httpx.MockTransport(lambda _: httpx.Response(200, json={"dofs": "none"}))
    with (
        Client(http_client=httpx.Client(transport=transport, base_url="http://t"), retries=0) as sdk,
        pytest.raises(ServerError, match=r"model info does not match.*dofs: Input should be a valid"),
    ):
        sdk.model_info()
    transport = httpx.MockTransport(lambda _: httpx.Response(200, content=b'{"event": "progress", \n'))
    with (
        Client(http_client=httpx.Client(transport=transport, base_url="http://t"), retries=0) as sdk,
        pytest.raises(ServerError, match="Invalid JSON"),
    ):
        sdk.fit_scan(np.zeros((3, 3)))


def test_chunks_that_leave_out_frames_are_a_server_error(
    client: TestClient, sequence_file: dict[str, Any]
) -> None:
    events = stream(client, "/v1/fit/sequence?chunk=2", files=sequence_file)
    with sdk_against(*events) as sdk:
        assert sdk.fit_sequence(np.zeros((5, 13348, 3))).coordinates.shape == (5, 46)
    gap = [e for e in events if not (e["event"] == "chunk" and e["start"] == 2)]
    with sdk_against(*gap) as sdk, pytest.raises(ServerError, match=r"frames \[4, 5\) follow frame 2"):
        sdk.fit_sequence(np.zeros((5, 13348, 3)))


# -- the OpenAPI document --------------------------------------------------------------------------------


def refs(node: Any) -> Iterator[str]:
    if isinstance(node, dict):
        for key, value in node.items():
            if key == "$ref" and isinstance(value, str):
                yield value
            else:
                yield from refs(value)
    elif isinstance(node, list):
        for value in node:
            yield from refs(value)


def schema_of(spec: dict[str, Any], path: str, method: str, status: str, media: str) -> Any:
    return spec["paths"][path][method]["responses"][status]["content"][media]["schema"]


def test_openapi_lists_the_response_models(client: TestClient) -> None:
    spec = client.get("/openapi.json").json()
    components = spec["components"]["schemas"]
    missing = {r for r in refs(spec) if r.removeprefix("#/components/schemas/") not in components}
    assert not missing
    ref = "#/components/schemas/{}".format
    json_answers = {
        ("/v1/model", "get"): "ModelInfo",
        ("/healthz", "get"): "Health",
        ("/readyz", "get"): "Ready",
        ("/v1/synthesize", "post"): "SynthesisJSON",
        ("/v1/fit/scan", "post"): "MeshFit",
        ("/v1/fit/sequence", "post"): "SequenceAnswer",
        ("/v1/upgrade", "post"): "UpgradeAnswer",
    }
    for (path, method), name in json_answers.items():
        assert schema_of(spec, path, method, "200", "application/json") == {"$ref": ref(name)}, path
    streams = {
        "/v1/fit/scan": "ScanFitEvent",
        "/v1/fit/sequence": "SequenceFitEvent",
        "/v1/upgrade": "UpgradeEvent",
    }
    for path, name in streams.items():
        assert schema_of(spec, path, "post", "200", "application/x-ndjson") == {"$ref": ref(name)}
        union = components[name]
        assert union["discriminator"]["propertyName"] == "event"
        assert set(union["discriminator"]["mapping"]) >= {"progress", "result", "error"}
        assert schema_of(spec, path, "post", "4XX", "application/problem+json") == {"$ref": ref("Problem")}
    mapping = components["SequenceFitEvent"]["discriminator"]["mapping"]
    assert mapping["chunk"] == ref("SequenceChunkEvent")
    assert components["WireArray"]["properties"]["data"]["contentEncoding"] == "base64"

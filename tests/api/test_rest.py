"""The REST API in process: operations, problem+json for a corpus of malformed requests, limits, health,
metrics and the OpenAPI document."""

from __future__ import annotations

import io
import json
import struct
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from bodyfit.api.rest.app import create_app
from bodyfit.api.settings import ServiceSettings
from bodyfit.service.core import BodyService, SynthRequest

UPLOAD_LIMIT_MB = 2.0


@pytest.fixture(scope="module")
def client(body_service: BodyService) -> Iterator[TestClient]:
    app = create_app(ServiceSettings(max_upload_mb=UPLOAD_LIMIT_MB), service=body_service)
    with TestClient(app, raise_server_exceptions=False) as c:
        yield c


def npz(**arrays: Any) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def test_model_info(client: TestClient) -> None:
    doc = client.get("/v1/model").json()
    assert len(doc["dofs"]) == 46 and doc["dofs"][0]["name"] == "pelvis_tilt"
    assert doc["shape"]["n_shape"] == 32 and doc["mesh"]["n_vertices"] == 13348


def test_synthesize_npz_matches_the_core(client: TestClient, body_service: BodyService) -> None:
    r = client.post("/v1/synthesize", json={"coordinates": {"elbow_flex_r": [0.2, 1.2]}, "faces": True})
    assert r.status_code == 200 and r.headers["content-type"] == "application/x-npz"
    z = np.load(io.BytesIO(r.content))
    q = body_service.model.skeleton.coordinates({"elbow_flex_r": np.array([0.2, 1.2])})
    ref = body_service.synthesize(SynthRequest(coordinates=q))
    assert np.array_equal(z["vertices"], ref.vertices) and z["faces"].shape == (26692, 3)


@pytest.mark.parametrize(
    ("fmt", "media", "magic"),
    [("ply", "application/x-ply", b"ply"), ("glb", "model/gltf-binary", b"glTF"), ("obj", "model/obj", b"")],
)
def test_synthesize_mesh_formats(client: TestClient, fmt: str, media: str, magic: bytes) -> None:
    r = client.post("/v1/synthesize", json={"format": fmt, "skeleton": fmt == "glb"})
    assert r.status_code == 200 and r.headers["content-type"] == media and r.content.startswith(magic)


def test_synthesize_json(client: TestClient) -> None:
    doc = client.post("/v1/synthesize", json={"format": "json"}).json()
    assert np.asarray(doc["vertices"]).shape == (1, 13348, 3) and len(doc["joint_names"]) == 19


def test_fit_scan_json_and_stream(client: TestClient, body_service: BodyService) -> None:
    verts = body_service.synthesize(SynthRequest(coordinates={"hip_flexion_l": 0.7})).vertices[0]
    files = {"file": ("body.npz", npz(points=verts))}
    doc = client.post("/v1/fit/scan", files=files).json()
    assert doc["fitted_as"] == "registered" and doc["report"]["distances"]["mean"] < 2.0
    with client.stream("POST", "/v1/fit/scan", files=files, headers={"accept": "application/x-ndjson"}) as r:
        events = [json.loads(line) for line in r.iter_lines() if line]
    assert [e["event"] for e in events] == ["progress", "progress", "result"]


def test_fit_sequence_streams_chunks(client: TestClient, body_service: BodyService) -> None:
    frames = body_service.synthesize(
        SynthRequest(coordinates={"knee_angle_l": np.linspace(0, 1, 5)})
    ).vertices
    files = {"file": ("seq.npz", npz(frames=frames))}
    with client.stream(
        "POST", "/v1/fit/sequence?chunk=2", files=files, headers={"accept": "application/x-ndjson"}
    ) as r:
        events = [json.loads(line) for line in r.iter_lines() if line]
    chunks = [(e["start"], e["stop"]) for e in events if e["event"] == "chunk"]
    assert chunks == [(0, 2), (2, 4), (4, 5)] and events[-1]["event"] == "result"
    assert events[-1]["limit_violations"] == 0


def npz_compressed(**arrays: Any) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def body_like(n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) points in a person-sized box, metres (1.7 m tall): no body, but no degenerate array either."""
    return np.random.default_rng(seed).uniform([-0.2, 0.0, -0.15], [0.2, 1.7, 0.15], (n, 3))


def _ply_header(n: int) -> bytes:
    return (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n".encode()
    )


# (what, method, path, request kwargs, status, words in the detail)
MALFORMED: list[tuple[str, str, str, dict[str, Any], int, str]] = [
    (
        "not json",
        "POST",
        "/v1/synthesize",
        {"content": b"{", "headers": {"content-type": "application/json"}},
        422,
        "not valid JSON",
    ),
    (
        "binary garbage",
        "POST",
        "/v1/synthesize",
        {"content": bytes(range(256)), "headers": {"content-type": "application/json"}},
        422,
        "JSON",
    ),
    ("json list", "POST", "/v1/synthesize", {"json": [1, 2]}, 422, "dictionary"),
    ("unknown key", "POST", "/v1/synthesize", {"json": {"pose": [[0.0]]}}, 422, "pose"),
    (
        "unknown dof",
        "POST",
        "/v1/synthesize",
        {"json": {"coordinates": {"knee_r": 1.0}}},
        422,
        "knee_angle_r",
    ),
    (
        "dof out of range",
        "POST",
        "/v1/synthesize",
        {"json": {"coordinates": {"knee_angle_r": -1.0}}},
        422,
        "range",
    ),
    (
        "NaN coordinate",
        "POST",
        "/v1/synthesize",
        {
            "content": b'{"coordinates": {"knee_angle_r": NaN}}',
            "headers": {"content-type": "application/json"},
        },
        422,
        "NaN",
    ),
    (
        "Infinity root",
        "POST",
        "/v1/synthesize",
        {"content": b'{"root": [[Infinity, 0, 0]]}', "headers": {"content-type": "application/json"}},
        422,
        "infinite",
    ),
    (
        "short coordinate rows",
        "POST",
        "/v1/synthesize",
        {"json": {"coordinates": [[0.0] * 10]}},
        422,
        "(B, 46)",
    ),
    (
        "ragged coordinates",
        "POST",
        "/v1/synthesize",
        {"json": {"coordinates": [[0.0] * 46, [0.0]]}},
        422,
        "coordinates",
    ),
    ("wrong shape count", "POST", "/v1/synthesize", {"json": {"shape": [[0.0] * 3]}}, 422, "32"),
    ("root of 2", "POST", "/v1/synthesize", {"json": {"root": [[0.0, 1.0]]}}, 422, "(1, 3)"),
    (
        "batch mismatch",
        "POST",
        "/v1/synthesize",
        {"json": {"shape": [[0.0] * 32] * 2, "root": [[0.0] * 3] * 3}},
        422,
        "shape",
    ),
    ("string coefficient", "POST", "/v1/synthesize", {"json": {"shape": [["a"] * 32]}}, 422, "number"),
    ("unknown format", "POST", "/v1/synthesize", {"json": {"format": "fbx"}}, 422, "format"),
    ("batch zero", "POST", "/v1/synthesize", {"json": {"batch": 0}}, 422, "batch"),
    ("batch too large", "POST", "/v1/synthesize", {"json": {"batch": 100000}}, 413, "split"),
    ("ply of a batch", "POST", "/v1/synthesize", {"json": {"batch": 2, "format": "ply"}}, 422, "npz or glb"),
    ("wrong method", "GET", "/v1/synthesize", {}, 405, "Method Not Allowed"),
    ("unknown path", "GET", "/v1/nothing", {}, 404, "Not Found"),
    ("scan without file", "POST", "/v1/fit/scan", {"data": {"units": "m"}}, 422, "file"),
    (
        "scan unknown suffix",
        "POST",
        "/v1/fit/scan",
        {"files": {"file": ("scan.xyz", b"1 2 3")}},
        422,
        "ply, obj",
    ),
    ("scan no suffix", "POST", "/v1/fit/scan", {"files": {"file": ("scan", b"1 2 3")}}, 422, "suffix"),
    (
        "scan bad units",
        "POST",
        "/v1/fit/scan",
        {"files": {"file": ("a.ply", b"ply")}, "data": {"units": "cm"}},
        422,
        "units",
    ),
    ("empty ply", "POST", "/v1/fit/scan", {"files": {"file": ("a.ply", b"")}}, 422, "empty"),
    (
        "truncated ply",
        "POST",
        "/v1/fit/scan",
        {"files": {"file": ("a.ply", _ply_header(1000) + struct.pack("<3f", 0, 0, 0) * 10)}},
        422,
        "PLY",
    ),
    (
        "huge ply header",
        "POST",
        "/v1/fit/scan",
        {"files": {"file": ("a.ply", _ply_header(10**12))}},
        422,
        "PLY",
    ),
    (
        "binary garbage ply",
        "POST",
        "/v1/fit/scan",
        {"files": {"file": ("a.ply", bytes(range(256)) * 40)}},
        422,
        "PLY",
    ),
    (
        "garbage obj",
        "POST",
        "/v1/fit/scan",
        {"files": {"file": ("a.obj", b"v 1 2\nf 1 2 3\n" * 10)}},
        422,
        "(N, 3)",
    ),
    (
        "too few points",
        "POST",
        "/v1/fit/scan",
        {"files": {"file": ("a.npz", npz(points=np.random.default_rng(0).normal(size=(50, 3))))}},
        422,
        "at least",
    ),
    (
        "NaN points only",
        "POST",
        "/v1/fit/scan",
        {"files": {"file": ("a.npz", npz(points=np.full((500, 3), np.nan)))}},
        422,
        "points",
    ),
    (
        "flat scan",
        "POST",
        "/v1/fit/scan",
        {
            "files": {
                "file": (
                    "a.npz",
                    npz(points=np.c_[np.random.default_rng(0).normal(size=(500, 2)), np.zeros(500)]),
                )
            }
        },
        422,
        "plane",
    ),
    (
        "npz wrong key",
        "POST",
        "/v1/fit/scan",
        {"files": {"file": ("a.npz", npz(xyz=np.zeros((500, 3))))}},
        422,
        "points",
    ),
    (
        "centimetres",
        "POST",
        "/v1/fit/scan",
        {"files": {"file": ("a.npz", npz(points=np.random.default_rng(0).normal(size=(500, 3)) * 50))}},
        422,
        "extent",
    ),
    (
        "oversized upload",
        "POST",
        "/v1/fit/scan",
        {"files": {"file": ("a.ply", b"0" * int(UPLOAD_LIMIT_MB * 2**20 + 10))}},
        413,
        "at most",
    ),
    (
        "sequence zero frames",
        "POST",
        "/v1/fit/sequence",
        {"files": {"file": ("s.npz", npz(frames=np.zeros((0, 13348, 3))))}},
        422,
        "T >= 1",
    ),
    (
        "sequence wrong key",
        "POST",
        "/v1/fit/sequence",
        {"files": {"file": ("s.npz", npz(poses=np.zeros((3, 72))))}},
        422,
        "frames",
    ),
    (
        "sequence wrong topology",
        "POST",
        "/v1/fit/sequence",
        {"files": {"file": ("s.npz", npz(frames=np.zeros((3, 6890, 3))))}},
        422,
        "13348",
    ),
    (
        "sequence integers",
        "POST",
        "/v1/fit/sequence",
        {"files": {"file": ("s.npz", npz(frames=np.zeros((3, 13348, 3), np.int32)))}},
        422,
        "floats",
    ),
    (
        "sequence not npz",
        "POST",
        "/v1/fit/sequence",
        {"files": {"file": ("s.npz", b"PK\x03\x04garbage")}},
        422,
        "npz",
    ),
    (
        "root overflowing float32",
        "POST",
        "/v1/synthesize",
        {"json": {"root": [[0, 1e308, 0]]}},
        422,
        "[-100, 100]",
    ),
    (
        "shape of a 100 km body",
        "POST",
        "/v1/synthesize",
        {"json": {"shape": [[1e6] * 32]}},
        422,
        "standard deviations and must lie within [-10, 10]",
    ),
    ("zero bodies glb", "POST", "/v1/synthesize", {"json": {"shape": [], "format": "glb"}}, 422, "0 bodies"),
    ("zero bodies npz", "POST", "/v1/synthesize", {"json": {"root": [], "format": "npz"}}, 422, "0 bodies"),
    (
        "zero bodies json",
        "POST",
        "/v1/synthesize",
        {"json": {"coordinates": {"knee_angle_r": []}, "format": "json"}},
        422,
        "0 bodies",
    ),
    ("batch as a string", "POST", "/v1/synthesize", {"json": {"batch": "2"}}, 422, "integer"),
    ("batch as a float", "POST", "/v1/synthesize", {"json": {"batch": 2.0}}, 422, "integer"),
    ("skeleton yes", "POST", "/v1/synthesize", {"json": {"skeleton": "yes"}}, 422, "boolean"),
    ("faces 1", "POST", "/v1/synthesize", {"json": {"faces": 1}}, 422, "boolean"),
    (
        "coordinate as a string",
        "POST",
        "/v1/synthesize",
        {"json": {"coordinates": {"knee_angle_r": "1"}}},
        422,
        "number",
    ),
    ("coordinate true", "POST", "/v1/synthesize", {"json": {"coordinates": [[True] * 46]}}, 422, "number"),
    (
        "sequence of zero frames",
        "POST",
        "/v1/fit/sequence",
        {"files": {"file": ("s.npz", npz_compressed(frames=np.zeros((5, 13348, 3), np.float32)))}},
        422,
        "frame 0 holds only zeros",
    ),
    (
        "sequence of constant frames",
        "POST",
        "/v1/fit/sequence",
        {"files": {"file": ("s.npz", npz_compressed(frames=np.ones((5, 13348, 3), np.float32)))}},
        422,
        "one point",
    ),
    (
        "sequence in millimetres",
        "POST",
        "/v1/fit/sequence",
        {"files": {"file": ("s.npz", npz(frames=np.stack([body_like(13348) * 1000.0] * 2)))}},
        422,
        "divide by 1000",
    ),
    (
        "scan in metres sent as mm",
        "POST",
        "/v1/fit/scan",
        {"files": {"file": ("a.npz", npz(points=body_like(2000)))}, "data": {"units": "mm"}},
        422,
        "units=m",
    ),
    (
        "sequence chunk zero",
        "POST",
        "/v1/fit/sequence?chunk=0",
        {"files": {"file": ("s.npz", b"")}},
        422,
        "chunk",
    ),
]


@pytest.mark.parametrize(
    ("method", "path", "kwargs", "status", "words"),
    [m[1:] for m in MALFORMED],
    ids=[m[0] for m in MALFORMED],
)
def test_malformed_requests_get_a_problem(
    client: TestClient, method: str, path: str, kwargs: dict[str, Any], status: int, words: str
) -> None:
    r = client.request(method, path, **kwargs)
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    doc = r.json()
    assert doc["status"] == status and doc["kind"] and doc["title"]
    assert words.lower() in doc["detail"].lower(), doc["detail"]
    assert "Traceback" not in r.text and 'File "' not in r.text


def test_a_two_frame_sequence_answers_valid_json(client: TestClient, body_service: BodyService) -> None:
    """Two frames have no jitter (a second difference needs three): null with the reason, valid JSON."""
    frames = body_service.synthesize(SynthRequest(coordinates={"knee_angle_l": [0.0, 0.5]})).vertices
    r = client.post("/v1/fit/sequence", files={"file": ("seq.npz", npz(frames=frames))})
    assert r.status_code == 200, r.text
    doc = json.loads(r.text, parse_constant=lambda c: pytest.fail(f"{c} in the JSON"))
    stats = doc["stats"]
    assert stats["jitter_ratio"] is None and stats["jitter_fit_mm"] is None
    assert "three consecutive frames" in stats["jitter_note"] and stats["frames"] == 2


def test_streamed_fits_refuse_bad_frames_and_scans_before_the_stream(client: TestClient) -> None:
    """Frames or a scan that cannot be a body get an HTTP 422 even when NDJSON was asked for."""
    ndjson = {"accept": "application/x-ndjson"}
    zero = npz_compressed(frames=np.zeros((3, 13348, 3), np.float32))
    r = client.post("/v1/fit/sequence", files={"file": ("s.npz", zero)}, headers=ndjson)
    assert r.status_code == 422 and "only zeros" in r.json()["detail"] and r.json()["field"] == "frames"
    files = {"file": ("a.npz", npz(points=body_like(2000)))}
    r = client.post("/v1/fit/scan", files=files, data={"units": "mm"}, headers=ndjson)
    assert r.status_code == 422 and r.json()["field"] == "units" and "units=mm" in r.json()["detail"]


def test_domain_errors_inside_the_work_are_422_streamed_or_not(
    client: TestClient, body_service: BodyService, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A model-layer input error raised by the fit itself (the scan fitter's ScanError): a 422 problem, or
    an NDJSON error event with status 422 and kind invalid_argument, never 'Internal error'."""
    from bodyfit.io.scans import ScanError

    def fit_mesh(*args: object, **kwargs: object) -> None:
        raise ScanError("only 4 points are left after thinning to a 1 cm grid")

    monkeypatch.setattr(body_service, "fit_mesh", fit_mesh)
    files = {"file": ("a.npz", npz(points=body_like(2000)))}
    r = client.post("/v1/fit/scan", files=files)
    assert r.status_code == 422 and r.json()["kind"] == "invalid_argument", r.text
    assert "only 4 points" in r.json()["detail"]
    with client.stream("POST", "/v1/fit/scan", files=files, headers={"accept": "application/x-ndjson"}) as r:
        events = [json.loads(line) for line in r.iter_lines() if line]
    error = events[-1]
    assert error["event"] == "error" and error["status"] == 422 and error["kind"] == "invalid_argument"
    assert "only 4 points" in error["detail"]


def test_ndjson_lines_never_carry_nan() -> None:
    from bodyfit.api.rest.jobs import _line

    assert _line({"x": float("nan"), "y": [float("inf"), 1.5]}) == b'{"x":null,"y":[null,1.5]}\n'


def test_the_corpus_is_large_enough() -> None:
    assert len(MALFORMED) >= 30


def test_server_keeps_serving_after_bad_input(client: TestClient) -> None:
    for _ in range(3):
        client.post("/v1/synthesize", content=b"\x00\xff", headers={"content-type": "application/json"})
    assert client.post("/v1/synthesize", json={}).status_code == 200


def test_health_ready_metrics_openapi(client: TestClient) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    assert client.get("/readyz").status_code == 200
    client.post("/v1/synthesize", json={})
    text = client.get("/metrics").text
    assert 'bodyfit_requests_total{operation="/v1/synthesize",outcome="200",transport="rest"}' in text
    assert "process_resident_memory_bytes" in text
    spec = client.get("/openapi.json").json()
    assert {"/v1/model", "/v1/synthesize", "/v1/fit/scan", "/v1/fit/sequence"} <= set(spec["paths"])


def test_not_ready_until_loaded(tmp_path: Any) -> None:
    app = create_app(ServiceSettings(assets=tmp_path))  # an empty asset folder: loading fails
    with TestClient(app, raise_server_exceptions=False) as c:
        app.state.bodyfit.loaded.wait(30)
        r = c.get("/readyz")
        assert r.status_code == 503 and "build-assets" in r.json()["detail"]
        r = c.get("/v1/model")
        assert r.status_code == 503 and r.headers["retry-after"] and "failed to load" in r.json()["detail"]

"""POST /v1/subjects: a rig from several uploads of one person, answered as JSON or streamed, with the
subject file in the answer; too few scans and undetermined joints are 422 / error events that say why."""

from __future__ import annotations

import base64
import io
import json
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from bodyfit.api.rest.app import create_app
from bodyfit.api.settings import ServiceSettings
from bodyfit.models.rig.subject import Subject
from bodyfit.service.core import BodyService, SynthRequest


@pytest.fixture(scope="module")
def client(body_service: BodyService) -> Iterator[TestClient]:
    app = create_app(ServiceSettings(max_upload_mb=8.0), service=body_service)
    with TestClient(app, raise_server_exceptions=False) as c:
        yield c


def uploads(body_service: BodyService, n: int) -> list[tuple[str, tuple[str, bytes]]]:
    """``n`` registered meshes (npz vertices) of one body, the elbows and knees a little bent each time."""
    shape = np.random.default_rng(3).normal(size=(1, body_service.model.n_shape)) * 0.5
    bend = np.linspace(0.1, 0.3, n)
    q = {"elbow_flex_r": bend, "knee_angle_l": bend, "arm_flex_l": bend}
    verts = body_service.synthesize(SynthRequest(shape=np.repeat(shape, n, 0), coordinates=q)).vertices
    out = []
    for k, v in enumerate(verts):
        buf = io.BytesIO()
        np.savez(buf, points=v)
        out.append(("files", (f"pose{k}.npz", buf.getvalue())))
    return out


def test_a_rig_from_uploads(client: TestClient, body_service: BodyService) -> None:
    """Three meshes of one body in the shape space: the rig fits them as well as the generic model; the
    subject file in the answer loads against the model; the joints the poses did not move are listed."""
    files: Any = uploads(body_service, 3)
    r = client.post("/v1/subjects", files=files, data={"allow_undetermined": "true"})
    assert r.status_code == 200, r.text
    doc = r.json()
    assert doc["scans"] == ["pose0.npz", "pose1.npz", "pose2.npz"]
    assert max(doc["personal_mm"]) < 2.0 and "hip_r" in doc["undetermined_joints"]
    subject = Subject.from_bytes(base64.b64decode(doc["subject"]), body_service.model)
    assert subject.scans == tuple(doc["scans"])
    assert subject.offsets.shape == (body_service.model.n_vertices, 3)


def test_undetermined_joints_and_too_few_scans_say_why(client: TestClient, body_service: BodyService) -> None:
    files: Any = uploads(body_service, 3)
    with client.stream("POST", "/v1/subjects", files=files, headers={"accept": "application/x-ndjson"}) as r:
        events = [json.loads(line) for line in r.iter_lines() if line]
    assert events[0]["event"] == "progress" and events[-1]["event"] == "error"
    assert "joints undetermined: hip_r" in events[-1]["detail"] and "allow" in events[-1]["detail"]
    r = client.post("/v1/subjects", files=files[:2])
    assert r.status_code == 422 and "at least 3 scans" in r.json()["detail"]
    r = client.post("/v1/subjects", files=files, data={"up": "sideways"})
    assert r.status_code == 422 and "up" in r.json()["detail"]


def test_the_sdk_builds_a_subject(client: TestClient, body_service: BodyService, tmp_path: Any) -> None:
    """`Client.build_subject` over the same app: progress events, then the result; the saved file loads."""
    from bodyfit.clients import Client

    seen: list[dict[str, Any]] = []
    points = [np.load(io.BytesIO(part[1][1]))["points"] for part in uploads(body_service, 3)]
    with Client("http://testserver", http_client=client) as sdk:
        out = sdk.build_subject(points, progress=seen.append, allow_undetermined=True)
    assert out.scans == ("scan0.npz", "scan1.npz", "scan2.npz") and max(out.personal_mm) < 2.0
    assert seen and seen[0]["stage"] == "rig"
    subject = Subject.load(out.save(tmp_path / "me.npz"), body_service.model)
    assert subject.scans == out.scans
    with pytest.raises(ValueError, match="up"):
        sdk.build_subject(points, up="sideways")

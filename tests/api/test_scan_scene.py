"""REST: a raw scan with no person in it (a room of planes, a box, a sphere) is answered "no person found in
the scan" with a 422 naming what was found, before any fitting, streamed or not; the service's check lets a
person in a cluttered scene through."""

from __future__ import annotations

import io
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from bodyfit.api.rest.app import create_app
from bodyfit.api.settings import ServiceSettings
from bodyfit.io.scans import scan_from_arrays
from bodyfit.service.core import BodyService, SynthRequest
from bodyfit.service.errors import InvalidInputError


@pytest.fixture(scope="module")
def client(body_service: BodyService) -> Iterator[TestClient]:
    with TestClient(create_app(ServiceSettings(), service=body_service), raise_server_exceptions=False) as c:
        yield c


def npz(**arrays: Any) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def room(rng: np.random.Generator) -> np.ndarray:
    """A floor and two walls, 4 m and 2.5 m high: 30,000 points."""
    a = rng.uniform(0.0, 1.0, (3, 10_000, 2))
    floor = np.column_stack([4 * a[0, :, 0], np.zeros(10_000), 4 * a[0, :, 1]])
    back = np.column_stack([4 * a[1, :, 0], 2.5 * a[1, :, 1], np.zeros(10_000)])
    side = np.column_stack([np.zeros(10_000), 2.5 * a[2, :, 1], 4 * a[2, :, 0]])
    return np.concatenate([floor, back, side])


def box(rng: np.random.Generator) -> np.ndarray:
    """A 0.5 x 0.4 x 0.4 m box's surface: 12,000 points."""
    size = np.array([0.5, 0.4, 0.4])
    points = rng.uniform(0.0, 1.0, (12_000, 3)) * size
    axis, side = rng.integers(0, 3, 12_000), rng.integers(0, 2, 12_000)
    points[np.arange(12_000), axis] = side * size[axis]
    return points


def sphere(rng: np.random.Generator) -> np.ndarray:
    """A sphere 0.8 m across: 12,000 points."""
    d = rng.normal(size=(12_000, 3))
    return 0.4 * d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize(("make", "found"), [(room, "large plane"), (box, "box ("), (sphere, "sphere (")])
@pytest.mark.parametrize("stream", [False, True])
def test_a_scan_with_no_person_is_a_422_naming_what_was_found(
    client: TestClient, make: Any, found: str, stream: bool
) -> None:
    points = make(np.random.default_rng(0))
    headers = {"accept": "application/x-ndjson"} if stream else {}
    files = {"file": ("scene.npz", npz(points=points))}
    # in metres: a room is larger than any body, which the reader's unit guess refuses
    r = client.post("/v1/fit/scan", files=files, data={"units": "m"}, headers=headers)
    assert r.status_code == 422, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    doc = r.json()
    assert doc["detail"].startswith("no person found in the scan: "), doc["detail"]
    assert found in doc["detail"] and doc["field"] == "file"


def cluttered(body_service: BodyService) -> tuple[np.ndarray, np.ndarray]:
    """A body with a floor under it and a box beside it (N, 3), and the box alone."""
    rng = np.random.default_rng(1)
    body = body_service.synthesize(SynthRequest(coordinates={"knee_angle_l": 0.5})).vertices[0]
    lo = body.min(axis=0)
    a = rng.uniform(0.0, 1.0, (40_000, 2))
    floor = np.column_stack(
        [lo[0] - 1.0 + 2.0 * a[:, 0], np.full(len(a), lo[1]), lo[2] - 1.0 + 2.0 * a[:, 1]]
    )
    side = box(rng) + np.array([lo[0], lo[1], body[:, 2].max() + 0.3])
    return np.concatenate([body[::2], floor, side]), side


def test_the_service_check_passes_a_person_in_a_cluttered_scene(body_service: BodyService) -> None:
    """A body with a floor under it and a box beside it passes the check (the fit separates it); the box
    alone does not."""
    scene, side = cluttered(body_service)
    body_service.check_scan(scan_from_arrays(scene, units="m"))
    with pytest.raises(InvalidInputError, match="no person found"):
        body_service.check_scan(scan_from_arrays(side, units="m"))


def test_a_fit_over_rest_separates_the_person_once(
    client: TestClient, body_service: BodyService, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The check before streaming separates the person from the scene, and the fit reuses it: one
    separation per request, and the report still says what was removed."""
    from bodyfit.models.fitting.scan import phases

    calls = []
    separate = phases.separate_person

    def counted(*args: Any, **kwargs: Any) -> Any:
        calls.append(1)
        return separate(*args, **kwargs)

    monkeypatch.setattr(phases, "separate_person", counted)
    scene, _ = cluttered(body_service)
    files = {"file": ("scene.npz", npz(points=scene))}
    r = client.post("/v1/fit/scan", files=files, data={"units": "m", "up": "+y", "facing": "+x"})
    assert r.status_code == 200, r.text
    assert len(calls) == 1
    assert r.json()["report"]["extra"]["scene"]["planes"]

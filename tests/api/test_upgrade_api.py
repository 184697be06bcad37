"""The upgrade operation over REST and through the SDK: chunks, files that load, errors."""

from __future__ import annotations

import dataclasses
import io
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from bodyfit.api.rest.app import create_app
from bodyfit.clients.errors import InvalidRequestError
from bodyfit.clients.rest_client import Client
from bodyfit.service.core import BodyService

SEQUENCE = Path(__file__).resolve().parents[1] / "data" / "smpl_format" / "cmu_131_smpl.npz"


@pytest.fixture(scope="module")
def client(body_service: BodyService) -> Iterator[Client]:
    with Client("http://testserver", http_client=TestClient(create_app(service=body_service))) as c:
        yield c


def test_upgrade_through_the_sdk(client: Client, tmp_path: Path) -> None:
    events: list[dict[str, object]] = []
    out = client.upgrade(SEQUENCE, progress=events.append, chunk=25)
    assert out.coordinates.shape == (60, 46) and out.joints.shape[0] == 60 and not out.bad_frames.any()
    assert out.summary["path"] == "a" and out.summary["limit_violations"] == 0
    assert out.summary["v2v_mean_mm"] < 20.0 and events
    paths = out.save(tmp_path, "walk")
    saved = np.load(paths["npz"])
    assert np.allclose(saved["coordinates"], out.coordinates)
    assert (
        paths["osim"].read_text().lstrip().startswith("<?xml") and "pelvis_tilt" in paths["mot"].read_text()
    )


def test_upgrade_errors(client: Client, body_service: BodyService, tmp_path: Path) -> None:
    pkl = tmp_path / "walk.pkl"
    pkl.write_bytes(b"\x80\x04K\x01.")
    with pytest.raises(InvalidRequestError, match="unpickle"):
        client.upgrade(pkl)
    buf = io.BytesIO()
    np.savez(buf, poses=np.zeros((3, 70)), mocap_framerate=30)
    with pytest.raises(InvalidRequestError, match=r"\(T, 72\)"):
        client.upgrade(buf.getvalue())


def test_a_server_without_a_model_file_runs_path_b(body_service: BodyService) -> None:
    unconfigured = dataclasses.replace(body_service, _smpl=None)
    with Client("http://t", http_client=TestClient(create_app(service=unconfigured))) as bare:
        out = bare.upgrade(SEQUENCE)
    assert out.summary["path"] == "b" and out.summary["v2v_mean_mm"] is None
    assert any("betas were not used" in note for note in out.summary["notes"])
    assert out.coordinates.shape == (60, 46) and out.summary["limit_violations"] == 0


def test_path_b_shape_hints_over_rest(body_service: BodyService) -> None:
    unconfigured = dataclasses.replace(body_service, _smpl=None)
    with Client("http://t", http_client=TestClient(create_app(service=unconfigured))) as bare:
        out = bare.upgrade(SEQUENCE, sex="male", height_m=1.9, mass_kg=95.0)
        assert any("height 1.9 m" in note and "stature 1.90 m" in note for note in out.summary["notes"])
        with pytest.raises(InvalidRequestError, match="height_m must be an adult's") as info:
            bare.upgrade(SEQUENCE, height_m=19.0)
        assert info.value.field == "height_m"
    with TestClient(create_app(service=unconfigured)) as raw:
        answer = raw.post("/v1/upgrade", files={"file": ("a.npz", SEQUENCE.read_bytes())}, data={"sex": "x"})
    assert answer.status_code == 422 and answer.json()["field"] == "sex" and "male" in answer.json()["detail"]


def test_path_a_says_hints_were_not_used(client: Client) -> None:
    out = client.upgrade(SEQUENCE, height_m=1.7)
    assert out.summary["path"] == "a" and any("hints were not used" in n for n in out.summary["notes"])


def _z_up_clip(frames: int) -> bytes:
    """The first frames of the test clip in AMASS's Z-up world (turned +90 degrees about x), as an .npz."""
    from bodyfit.io.smpl import read_smpl_sequence
    from bodyfit.models.upgrade.axes import turned
    from bodyfit.models.upgrade.smpl_model import load_smpl_model, rodrigues

    seq = read_smpl_sequence(SEQUENCE)
    smpl = load_smpl_model(SEQUENCE.parent / "smpl_like_model.npz")
    z_up = turned(seq, smpl, rodrigues(np.array([np.pi / 2, 0.0, 0.0])))
    buf = io.BytesIO()
    poses = z_up.poses[:frames].reshape(frames, 72)
    np.savez(buf, poses=poses, trans=z_up.trans[:frames], betas=seq.betas, mocap_framerate=seq.fps)
    return buf.getvalue()


def test_the_up_axis_over_rest_and_the_sdk(client: Client, body_service: BodyService) -> None:
    """A Z-up upload needs no field (the summary says what was detected); ``up`` names it, with the same
    coordinates; a value naming no axis is refused naming the field, by the SDK before sending."""
    data = _z_up_clip(10)
    found = client.upgrade(data)
    assert found.summary["up_axis"] == "+z" and found.summary["up_given"] is False
    assert any(n.startswith("the input's up axis: +z (detected") for n in found.summary["notes"])
    named = client.upgrade(data, up="z")
    assert named.summary["up_axis"] == "+z" and named.summary["up_given"] is True
    assert np.degrees(np.abs(named.coordinates - found.coordinates)).max() < 0.5
    with pytest.raises(ValueError, match="up must be one of"):
        client.upgrade(data, up="north")
    with TestClient(create_app(service=body_service)) as raw:
        answer = raw.post("/v1/upgrade", files={"file": ("a.npz", data)}, data={"up": "north"})
    assert answer.status_code == 422 and answer.json()["field"] == "up" and "+z" in answer.json()["detail"]


def test_rotation_matrix_uploads_are_refused_naming_axis_angle(client: Client) -> None:
    buf = io.BytesIO()
    np.savez(buf, poses=np.tile(np.eye(3).reshape(1, 1, 9), (4, 24, 1)).reshape(4, 216), mocap_framerate=30)
    with pytest.raises(InvalidRequestError, match="rotation matrices") as info:
        client.upgrade(buf.getvalue())
    assert "expected axis-angle in radians" in str(info.value) and info.value.field == "file"

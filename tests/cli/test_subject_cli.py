"""``--subject`` on the command line (synth, fit scan, fit sequence, upgrade) and ``bodyfit rig --server``:
the subject's body is used in this process and through a server; a subject with --shape or shape hints, or a
file that is not a subject, exits with status 2 and says why."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from typer.testing import CliRunner

import bodyfit.clients.rest_client as rest_client
from bodyfit.api.rest.app import create_app
from bodyfit.cli import app
from bodyfit.models.rig.subject import Subject
from bodyfit.service.core import BodyService, SynthRequest
from tests.service.subject_files import make_subject

runner = CliRunner()
DATA = Path(__file__).resolve().parents[1] / "data" / "smpl_format"


@pytest.fixture(scope="module")
def subject(body_service: BodyService) -> Subject:
    return make_subject(body_service.model, seed=7)


@pytest.fixture
def subject_file(subject: Subject, tmp_path: Path) -> Path:
    return subject.save(tmp_path / "subject.npz")


@pytest.fixture
def served(body_service: BodyService, monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """The REST SDK's Client, as the commands build it, talking to an in-process server."""
    with TestClient(create_app(service=body_service)) as http:
        base = rest_client.Client

        class InProcess(base):  # type: ignore[misc, valid-type]
            def __init__(self, url: str | None = None, **kwargs: Any) -> None:
                super().__init__(url, http_client=http, **kwargs)

        monkeypatch.setattr(rest_client, "Client", InProcess)
        yield "http://testserver"


def posed(body_service: BodyService, subject: Subject, bend: np.ndarray) -> np.ndarray:
    q = body_service.model.skeleton.coordinates({"knee_angle_r": bend, "elbow_flex_l": bend})
    return body_service.synthesize(SynthRequest(coordinates=q, subject=subject.to_bytes())).vertices


def test_synth_with_a_subject_here_and_on_a_server(
    body_service: BodyService, subject: Subject, subject_file: Path, tmp_path: Path, served: str
) -> None:
    expected = posed(body_service, subject, np.array([0.8]))
    for where in ([], ["--server", served]):
        out = tmp_path / f"body{len(where)}.npz"
        args = [
            "synth",
            str(out),
            "-c",
            "knee_angle_r=0.8",
            "-c",
            "elbow_flex_l=0.8",
            "--subject",
            str(subject_file),
        ]
        result = runner.invoke(app, [*args, *where])
        assert result.exit_code == 0, result.output
        assert np.array_equal(np.load(out)["vertices"], expected), where
    both = runner.invoke(
        app, ["synth", str(tmp_path / "x.npz"), "--subject", str(subject_file), "--shape", "1"]
    )
    assert both.exit_code == 2 and "--subject or --shape" in both.output
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a subject")
    refused = runner.invoke(app, ["synth", str(tmp_path / "x.npz"), "--subject", str(bad)])
    assert (
        refused.exit_code == 2
        and "not a subject file" in refused.output
        and "Traceback" not in refused.output
    )


def test_fit_scan_and_sequence_with_a_subject(
    body_service: BodyService, subject: Subject, subject_file: Path, tmp_path: Path
) -> None:
    frames = posed(body_service, subject, np.array([0.3, 0.6, 0.9]))
    mesh = tmp_path / "mesh.npz"
    np.savez(mesh, vertices=frames[0])
    result = runner.invoke(
        app, ["fit", "scan", str(mesh), "--subject", str(subject_file), "--out", str(tmp_path / "f")]
    )
    assert result.exit_code == 0, result.output
    assert np.array_equal(np.load(tmp_path / "f" / "fit.npz")["shape"][0], subject.shape)
    sequence = tmp_path / "walk.npz"
    np.savez(sequence, frames=frames)
    out = tmp_path / "s"
    result = runner.invoke(app, ["fit", str(sequence), "--subject", str(subject_file), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert np.array_equal(np.load(out / "walk.npz")["shape"], subject.shape)


def test_upgrade_with_a_subject_writes_its_scales(
    body_service: BodyService, subject: Subject, subject_file: Path, tmp_path: Path
) -> None:
    with np.load(DATA / "cmu_131_smpl.npz") as npz:
        arrays = {k: npz[k] for k in npz.files}
    arrays["poses"], arrays["trans"] = arrays["poses"][:8], arrays["trans"][:8]
    clip = tmp_path / "clip.npz"
    np.savez(clip, **arrays)
    args = [
        "upgrade",
        str(clip),
        "--smpl-model",
        str(DATA / "smpl_like_model.npz"),
        "--out",
        str(tmp_path / "out"),
    ]
    result = runner.invoke(app, [*args, "--subject", str(subject_file)])
    assert result.exit_code == 0, result.output
    saved = np.load(tmp_path / "out" / "clip.npz")
    assert np.array_equal(saved["shape"], subject.shape)
    summary = json.loads((tmp_path / "out" / "clip.json").read_text())
    assert any("subject file" in note for note in summary["notes"])
    hinted = runner.invoke(app, [*args, "--subject", str(subject_file), "--sex", "male"])
    assert hinted.exit_code == 2 and "give a subject or --sex" in hinted.output


def test_rig_on_a_server(body_service: BodyService, tmp_path: Path, served: str) -> None:
    shape = np.random.default_rng(3).normal(size=(1, body_service.model.n_shape)) * 0.5
    bend = np.linspace(0.1, 0.3, 3)
    q = {"elbow_flex_r": bend, "knee_angle_l": bend, "arm_flex_l": bend}
    verts = body_service.synthesize(SynthRequest(shape=np.repeat(shape, 3, 0), coordinates=q)).vertices
    scans = []
    for k, v in enumerate(verts):
        path = tmp_path / f"pose{k}.npz"
        np.savez(path, points=v)
        scans.append(str(path))
    out = tmp_path / "subject"
    result = runner.invoke(
        app, ["rig", *scans, "--out", str(out), "--server", served, "--allow-undetermined"]
    )
    assert result.exit_code == 0, result.output
    subject = Subject.load(out / "subject.npz", body_service.model)
    assert subject.scans == ("pose0.npz", "pose1.npz", "pose2.npz")
    assert json.loads((out / "subject.json").read_text())["server"] == served
    assert (out / "rest.ply").read_bytes().startswith(b"ply")


def test_batch_upgrade_with_a_subject(
    subject: Subject, subject_file: Path, tmp_path: Path, served: str
) -> None:
    """Every sequence of the dataset upgraded as the subject's body, on a server and in this process."""
    with np.load(DATA / "cmu_131_smpl.npz") as npz:
        arrays = {k: npz[k] for k in npz.files}
    arrays["poses"], arrays["trans"] = arrays["poses"][:6], arrays["trans"][:6]
    dataset = tmp_path / "amass" / "me"
    dataset.mkdir(parents=True)
    np.savez(dataset / "walk.npz", **arrays)
    for backend in (served, "local"):
        out = tmp_path / f"out_{backend[:4]}"
        args = ["batch-upgrade", str(tmp_path / "amass"), str(out), "--backend", backend]
        result = runner.invoke(app, [*args, "--subject", str(subject_file)])
        assert result.exit_code == 0, result.output
        assert np.array_equal(np.load(out / "me" / "walk.npz")["shape"], subject.shape), backend

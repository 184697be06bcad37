"""`bodyfit rig`: three meshes of one person in, the subject file, its report, the rest mesh and an ONNX
decoder out (parity with torch); too few scans and a bad unit exit with status 2 and say why."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from typer.testing import CliRunner

from bodyfit.cli import app
from bodyfit.models.body.model import BodyModel
from bodyfit.models.rig.subject import Subject

runner = CliRunner()


def test_rig_writes_a_subject_with_an_onnx_decoder(tmp_path: Path) -> None:
    import onnxruntime as ort
    import trimesh

    model = BodyModel.load()
    bend = np.array([0.3, 0.8, 1.3])
    q = model.skeleton.coordinates({"knee_angle_r": bend, "elbow_flex_l": bend, "hip_flexion_l": bend})
    shape = np.tile(np.eye(model.n_shape)[:1], (3, 1))
    verts = model.forward(shape, q).vertices.numpy()
    paths = []
    for k, v in enumerate(verts):
        paths.append(tmp_path / f"pose{k}.ply")
        trimesh.Trimesh(v * 1000.0, model.faces, process=False).export(paths[-1])  # millimetres
    out = tmp_path / "me"
    result = runner.invoke(app, ["rig", *map(str, paths), "--allow-undetermined", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "pose0.ply:" in result.output and "undetermined joints (from the shape space):" in result.output
    report = json.loads((out / "subject.json").read_text())
    assert report["scans"] == ["pose0.ply", "pose1.ply", "pose2.ply"] and max(report["personal_mm"]) < 1.0
    subject = Subject.load(out / "subject.npz", model)
    assert abs(subject.shape[0] - 1.0) < 0.1  # the first bone coefficient, as the meshes were made
    session = ort.InferenceSession(str(out / "subject.onnx"), providers=["CPUExecutionProvider"])
    feeds = {"shape": subject.shape[None].astype(np.float32), "coordinates": q[1:2].astype(np.float32)}
    feeds["root"] = np.zeros((1, 3), np.float32)
    onnx_vertices = session.run(["vertices"], feeds)[0]
    with torch.no_grad():
        c = torch.as_tensor(subject.shape[None])
        ref = subject.decoder(model, torch.float64)(
            c, torch.as_tensor(q[1:2]), torch.zeros(1, 3, dtype=torch.float64)
        )
    assert np.abs(onnx_vertices - ref[0].numpy()).max() < 1e-5
    assert len(trimesh.load_mesh(out / "rest.ply", process=False).vertices) == model.n_vertices


def test_rig_refuses_too_few_scans_and_bad_units(tmp_path: Path) -> None:
    import trimesh

    model = BodyModel.load()
    path = tmp_path / "one.ply"
    trimesh.Trimesh(model.forward(None, None).vertices.numpy()[0], model.faces, process=False).export(path)
    few = runner.invoke(app, ["rig", str(path), str(path), "--out", str(tmp_path / "o")])
    assert few.exit_code == 2 and "at least 3 scans" in few.output
    units = runner.invoke(app, ["rig", str(path), "--units", "cm", "--out", str(tmp_path / "o")])
    assert units.exit_code == 2 and "Invalid value for '--units'" in units.output

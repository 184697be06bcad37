"""`bodyfit batch-fit` and its back-ends: the service in this process and a Ray pool; a bad scan is
reported, the rest are fitted, a second run resumes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from bodyfit.cli import app
from bodyfit.models.body.model import BodyModel

runner = CliRunner()


def scans(root: Path, n_good: int = 1) -> tuple[Path, np.ndarray]:
    """a/m<k>.ply: registered meshes of the model in millimetres (knee 0.9 rad); b/broken.ply: not a
    mesh; notes.txt and .cache/old.ply: not scans. Returns the root and the true vertices (n_good, V, 3) m."""
    import trimesh

    model = BodyModel.load()
    q = model.skeleton.coordinates({"knee_angle_r": 0.9, "hip_flexion_r": 0.6}, batch=n_good)
    shape = np.random.default_rng(1).normal(size=(n_good, model.n_shape)) * 0.5
    verts = model.forward(shape, q, np.tile([0.1, 0.9, 0.0], (n_good, 1))).vertices.numpy()
    for sub in ("a", "b", ".cache"):
        (root / sub).mkdir(parents=True)
    for k, v in enumerate(verts):
        trimesh.Trimesh(v * 1000.0, model.faces, process=False).export(root / "a" / f"m{k}.ply")
    (root / "b" / "broken.ply").write_text("ply\nthis is not a mesh\n")
    (root / "notes.txt").write_text("not a scan")
    (root / ".cache" / "old.ply").write_text("ignored: hidden folder")
    return root, verts


def test_batch_fit_in_this_process(tmp_path: Path) -> None:
    """The good mesh is fitted and written (npz, ply, json), the broken one listed with status 1; run again,
    the finished scan is skipped."""
    import trimesh

    root, verts = scans(tmp_path / "scans")
    out = tmp_path / "out"
    first = runner.invoke(app, ["batch-fit", str(root), str(out)])
    assert first.exit_code == 1, first.output
    assert "FAILED b/broken.ply" in first.output and "1 fitted, 0 already done, 1 failed" in first.output
    assert sorted(p.name for p in (out / "a").iterdir()) == ["m0.json", "m0.npz", "m0.ply"]
    report = json.loads((out / "a" / "m0.json").read_text())
    assert report["scan"] == "m0.ply" and report["fitted_as"] == "registered" and report["confident"]
    data = np.load(out / "a" / "m0.npz")
    model = BodyModel.load()
    assert abs(data["coordinates"][model.dof_names.index("knee_angle_r")] - 0.9) < 0.1
    assert str(data["fitted_as"]) == "registered" and list(data["dof_names"]) == model.dof_names
    mesh = trimesh.load_mesh(out / "a" / "m0.ply", process=False)
    np.testing.assert_array_equal(mesh.faces, model.faces)
    assert np.linalg.norm(mesh.vertices - verts[0], axis=1).mean() < 0.003  # metres, in the scan's frame
    again = runner.invoke(app, ["batch-fit", str(root), str(out)])
    assert "0 fitted, 1 already done, 1 failed" in again.output


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--backend", "nope"], "error: unknown backend 'nope'"),
        (["--up", "sideways"], "error: "),
        (["--units", "cm"], "Invalid value for '--units'"),
        (["--up", "+z", "--facing", "-z"], "facing must be perpendicular to up"),
    ],
)
def test_batch_fit_refuses_bad_options(tmp_path: Path, option: list[str], message: str) -> None:
    """A bad back-end, hint or unit exits with status 2 and one error line, before any model is loaded."""
    result = runner.invoke(app, ["batch-fit", str(tmp_path), str(tmp_path / "o"), *option])
    assert result.exit_code == 2 and message in result.output, result.output


def test_the_ray_backend_fits_scans(tmp_path: Path) -> None:
    """Two actors, two scans in flight: both fitted, the bad one reported, through the command."""
    ray = pytest.importorskip("ray")
    root, verts = scans(tmp_path / "scans", n_good=2)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        result = runner.invoke(
            app, ["batch-fit", str(root), str(tmp_path / "out"), "--backend", "ray", "--concurrency", "2"]
        )
    finally:
        ray.shutdown()
    assert result.exit_code == 1, result.output
    assert "2 fitted, 0 already done, 1 failed" in result.output and "FAILED b/broken.ply" in result.output
    for k in range(2):
        fitted = np.load(tmp_path / "out" / "a" / f"m{k}.npz")["vertices"]
        assert np.linalg.norm(fitted - verts[k], axis=1).mean() < 0.003

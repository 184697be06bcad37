"""batch_fit (the SDK): finds the scans of a folder tree, resumes, reports failures without stopping, sends
its options to a server, and writes readable files."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bodyfit.clients.batch_fit import FIT_OPTIONS, batch_fit, find_scans, fit_files, ply_bytes, server_fitter
from bodyfit.clients.uploads import SCAN_FORMATS
from bodyfit.io.scans import FORMATS, load_scan
from bodyfit.service.core import BodyService
from bodyfit.service.jobs import Job


def test_the_sdk_knows_the_servers_scan_formats() -> None:
    assert SCAN_FORMATS == FORMATS


def test_find_scans_walks_the_tree(tmp_path: Path) -> None:
    """Scan extensions in any case, recursively, sorted; other files and hidden folders are not scans; two
    scans that would write the same outputs are refused, both named."""
    for name in ("b/z.PLY", "a/y.obj", "a/x.v2.pcd", "a/readme.md", ".git/q.ply", "c.npz"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_bytes(b"")
    assert [str(p.relative_to(tmp_path)) for p in find_scans(tmp_path)] == [
        "a/x.v2.pcd",
        "a/y.obj",
        "b/z.PLY",
        "c.npz",
    ]
    (tmp_path / "a" / "y.stl").write_bytes(b"")
    with pytest.raises(ValueError, match=r"y\.obj and .*y\.stl would both write a/y"):
        find_scans(tmp_path)


def test_ply_bytes_reads_back(tmp_path: Path) -> None:
    import trimesh

    rng = np.random.default_rng(0)
    vertices, faces = rng.normal(size=(7, 3)), rng.integers(0, 7, size=(5, 3))
    path = tmp_path / "m.ply"
    path.write_bytes(ply_bytes(vertices, faces))
    mesh = trimesh.load_mesh(path, process=False)
    np.testing.assert_allclose(mesh.vertices, vertices.astype(np.float32))
    np.testing.assert_array_equal(mesh.faces, faces)


def test_resumes_and_reports_failures(body_service: BodyService, tmp_path: Path) -> None:
    """A callable back-end over the service: the good scan's files (json written last, no .part left), the
    bad one's message, and a second run that only retries the failure. A dotted stem keeps its name."""
    import trimesh

    model = body_service.model
    root = tmp_path / "scans"
    (root / "s").mkdir(parents=True)
    verts = model.forward(np.zeros((1, model.n_shape))).vertices.numpy()[0]
    trimesh.Trimesh(verts, model.faces, process=False).export(root / "s" / "body.v1.ply")
    (root / "s" / "bad.stl").write_bytes(b"solid nothing\nendsolid\n")
    calls: list[str] = []

    def fit(path: Path) -> dict[str, bytes]:
        calls.append(path.name)
        result = body_service.fit_mesh(load_scan(path), Job())
        report = result.report.to_dict()
        names = (model.dof_names, model.joint_names)
        return fit_files(path.name, result.fitted_as, result.arrays(), *names, report, model.faces)

    out = tmp_path / "out"
    first = batch_fit(root, out, concurrency=2, backend=fit, progress=False)
    assert first.done == ["s/body.v1.ply"] and list(first.failed) == ["s/bad.stl"]
    assert "holds no points" in first.failed["s/bad.stl"]
    assert first.summary().startswith("1 fitted, 0 already done, 1 failed")
    assert sorted(p.name for p in (out / "s").iterdir()) == ["body.v1.json", "body.v1.npz", "body.v1.ply"]
    assert np.load(out / "s" / "body.v1.npz")["shape"].shape == (model.n_shape,)
    calls.clear()
    again = batch_fit(root, out, backend=fit, progress=False)
    assert again.skipped == ["s/body.v1.ply"] and calls == ["bad.stl"] and not again.done


def test_options_go_to_the_server(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Units and hints go with every scan; the model's faces are asked for once; options are checked."""
    import bodyfit.clients.rest_client

    sent: list[dict[str, Any]] = []
    asked_faces: list[bool] = []

    class Fit:
        fitted_as = "raw scan"
        shape, coordinates, root = np.zeros(4), np.zeros(3), np.zeros(3)
        vertices, joints, to_model = np.zeros((3, 3)), np.zeros((2, 3)), np.eye(4)
        dof_names, joint_names = ("a", "b", "c"), ("p", "q")
        report: dict[str, Any] = {"confident": True}  # noqa: RUF012 (a stand-in answer)

    class Synthesis:
        faces = np.array([[0, 1, 2]])

    class FakeClient:
        def __init__(self, url: str, **_: object) -> None:
            self.url = url

        def fit_scan(self, path: Path, **options: Any) -> Fit:
            sent.append(options)
            return Fit()

        def synthesize(self, faces: bool) -> Synthesis:
            asked_faces.append(faces)
            return Synthesis()

    monkeypatch.setattr(bodyfit.clients.rest_client, "Client", FakeClient)
    root = tmp_path / "scans"
    root.mkdir()
    for name in ("a.ply", "b.pcd"):
        (root / name).write_bytes(b"")
    report = batch_fit(
        root, tmp_path / "out", backend="http://server:8000", progress=False, up="+z", units="mm"
    )
    assert sorted(report.done) == ["a.ply", "b.pcd"]
    assert sent == [{"up": "+z", "units": "mm"}] * 2 and asked_faces == [True]
    assert (tmp_path / "out" / "b.ply").stat().st_size > 0 and "raw scan" in (
        tmp_path / "out" / "b.json"
    ).read_text()
    assert server_fitter("http://server:8000")(root / "a.ply")["npz"]
    with pytest.raises(
        ValueError, match=r"unknown batch_fit option\(s\) colour; allowed: " + ", ".join(FIT_OPTIONS)
    ):
        batch_fit(root, tmp_path / "o", backend="http://server:8000", colour="red")
    with pytest.raises(ValueError, match="need a server URL back-end"):
        batch_fit(root, tmp_path / "o", backend=lambda p: {}, up="+z")
    with pytest.raises(ValueError, match="not a server URL"):
        batch_fit(root, tmp_path / "o", backend="local")
    with pytest.raises(FileNotFoundError, match="is not a folder of scans"):
        batch_fit(root / "a.ply", tmp_path / "o")

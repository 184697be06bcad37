"""batch_upgrade: walks an AMASS-style tree, resumes, reports failures without stopping; local, callable and
Ray back-ends."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest

from bodyfit.clients.batch import batch_upgrade, find_sequences
from bodyfit.io.smpl import read_smpl_sequence
from bodyfit.service.core import BodyService

DATA = Path(__file__).resolve().parents[1] / "data" / "smpl_format"


def dataset(root: Path) -> Path:
    """subject_a/walk.npz (good), subject_a/shape.npz (AMASS betas file), subject_b/broken.npz (no poses)."""
    (root / "subject_a").mkdir(parents=True)
    (root / "subject_b").mkdir()
    shutil.copy(DATA / "cmu_131_smpl.npz", root / "subject_a" / "walk.npz")
    np.savez(root / "subject_a" / "shape.npz", betas=np.zeros(16))
    np.savez(root / "subject_b" / "broken.npz", trans=np.zeros((3, 3)))
    return root


def test_resumes_and_reports_failures(body_service: BodyService, tmp_path: Path) -> None:
    root = dataset(tmp_path / "amass")
    assert [p.name for p in find_sequences(root)] == ["walk.npz", "broken.npz"]
    calls: list[str] = []

    def upgrade(path: Path) -> dict[str, bytes]:
        calls.append(path.name)
        return body_service.upgrade_files(body_service.upgrade(read_smpl_sequence(path)), path.stem)

    out = tmp_path / "out"
    first = batch_upgrade(root, out, concurrency=2, backend=upgrade, progress=False)
    assert first.done == ["subject_a/walk.npz"] and list(first.failed) == ["subject_b/broken.npz"]
    assert "poses" in first.failed["subject_b/broken.npz"]
    for ext in ("npz", "json", "osim", "mot"):
        assert (out / "subject_a" / f"walk.{ext}").stat().st_size > 0
    assert not list(out.rglob("*.part"))
    calls.clear()
    again = batch_upgrade(root, out, backend=upgrade, progress=False)
    assert again.skipped == ["subject_a/walk.npz"] and calls == ["broken.npz"] and not again.done


def test_the_local_backend_without_a_model_file_upgrades_from_rotations(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`--backend local` with no SMPL-family model file (none given, $BODYFIT_SMPL_MODEL unset) loads the
    service without one, so upgrades take path (b), as `bodyfit upgrade` and the server do; a file that is
    not there is still an error (loading is stubbed: what the backend asks for is tested)."""
    from bodyfit.clients.batch import LocalUpgrader
    from bodyfit.models.upgrade.smpl_model import ENV_VAR, SmplModelError

    asked: list[object] = []

    def load(**kwargs: object) -> None:
        asked.append(kwargs["smpl_model"])

    monkeypatch.delenv(ENV_VAR, raising=False)
    monkeypatch.setattr(BodyService, "load", load)
    LocalUpgrader()
    monkeypatch.setenv(ENV_VAR, str(DATA / "smpl_like_model.npz"))
    LocalUpgrader()
    assert asked == [None, DATA / "smpl_like_model.npz"]
    with pytest.raises(SmplModelError, match="does not exist"):
        LocalUpgrader(tmp_path / "missing.npz")


def test_ray_backend(tmp_path: Path) -> None:
    ray = pytest.importorskip("ray")
    root = tmp_path / "amass"
    (root / "s").mkdir(parents=True)
    shutil.copy(DATA / "cmu_131_smpl.npz", root / "s" / "walk.npz")
    ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False)
    try:
        report = batch_upgrade(root, tmp_path / "out", 1, "ray", DATA / "smpl_like_model.npz", progress=False)
    finally:
        ray.shutdown()
    assert report.done == ["s/walk.npz"] and not report.failed
    saved = np.load(tmp_path / "out" / "s" / "walk.npz")
    assert saved["coordinates"].shape == (60, 46)


def test_the_up_axis_goes_to_the_server(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """batch_upgrade(up=) sends the axis with every sequence to a server back-end; with a callable
    back-end, which applies its own, it is refused."""
    import bodyfit.clients.rest_client
    from bodyfit.clients.batch import server_upgrader

    sent: list[str | None] = []

    class Answer:
        files: ClassVar[dict[str, bytes]] = {"json": b"{}"}

    class FakeClient:
        def __init__(self, url: str, **_: object) -> None:
            self.url = url

        def upgrade(self, path: Path, up: str | None = None, subject: bytes | None = None) -> Answer:
            sent.append(up)
            return Answer()

    monkeypatch.setattr(bodyfit.clients.rest_client, "Client", FakeClient)
    root = dataset(tmp_path / "amass")
    report = batch_upgrade(root, tmp_path / "out", backend="http://server:8000", progress=False, up="+z")
    assert sent == ["+z", "+z"] and report.done
    assert server_upgrader("http://server:8000")(root / "subject_a" / "walk.npz") == Answer.files
    assert sent[-1] is None  # no axis: the server detects it
    batch_upgrade(root, tmp_path / "out3", progress=False)
    assert sent[-2:] == [None, None]  # the default back-end is the SDK's client of a local server
    with pytest.raises(ValueError, match="needs a server URL"):
        batch_upgrade(root, tmp_path / "out2", backend=lambda p: {}, progress=False, up="+z")

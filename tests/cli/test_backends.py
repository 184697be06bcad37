"""`bodyfit batch-upgrade` and its back-ends: the service in this process, a Ray pool, a server; a bad
sequence is reported and the rest are upgraded."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from bodyfit.cli import app
from bodyfit.cli.backends import LocalUpgrader, upgrader
from bodyfit.service.core import BodyService

runner = CliRunner()
DATA = Path(__file__).resolve().parents[1] / "data" / "smpl_format"


def dataset(root: Path) -> Path:
    """s/walk.npz (the CMU test clip), s/shape.npz (AMASS betas, not a sequence), t/broken.npz (no poses)."""
    (root / "s").mkdir(parents=True)
    (root / "t").mkdir()
    shutil.copy(DATA / "cmu_131_smpl.npz", root / "s" / "walk.npz")
    np.savez(root / "s" / "shape.npz", betas=np.zeros(16))
    np.savez(root / "t" / "broken.npz", trans=np.zeros((3, 3)))
    return root


def test_the_local_backend_without_a_model_file_upgrades_from_rotations(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`--backend local` with no SMPL-family model file (none given, $BODYFIT_SMPL_MODEL unset) loads the
    service without one, so upgrades take path (b), as `bodyfit upgrade` and the server do; a file that is
    not there is still an error (loading is stubbed: what the backend asks for is tested)."""
    from bodyfit.models.upgrade.smpl_model import ENV_VAR, SmplModelError

    asked: list[object] = []

    def load(**kwargs: object) -> None:
        asked.append(kwargs["smpl_model"])

    monkeypatch.delenv(ENV_VAR, raising=False)
    monkeypatch.setattr(BodyService, "load", load)
    assert isinstance(upgrader("local"), LocalUpgrader)
    monkeypatch.setenv(ENV_VAR, str(DATA / "smpl_like_model.npz"))
    LocalUpgrader()
    assert asked == [None, DATA / "smpl_like_model.npz"]
    with pytest.raises(SmplModelError, match="does not exist"):
        LocalUpgrader(tmp_path / "missing.npz")


def test_a_backend_is_named_or_refused() -> None:
    assert callable(upgrader("http://127.0.0.1:9", 2))
    with pytest.raises(ValueError, match=r"unknown backend 'locale': give local, ray, ray://host:port"):
        upgrader("locale")


def test_batch_upgrade_in_this_process(tmp_path: Path) -> None:
    """The command upgrades the good sequence with the given model file (path a), lists the bad one and
    exits with status 1; run again, it skips the finished sequence."""
    root, out = dataset(tmp_path / "amass"), tmp_path / "out"
    args = ["batch-upgrade", str(root), str(out), "--smpl-model", str(DATA / "smpl_like_model.npz")]
    first = runner.invoke(app, args)
    assert first.exit_code == 1, first.output
    assert "FAILED t/broken.npz" in first.output and "1 upgraded, 0 already done, 1 failed" in first.output
    assert json.loads((out / "s" / "walk.json").read_text())["path"] == "a"
    assert {p.suffix for p in (out / "s").iterdir()} == {".npz", ".json", ".osim", ".mot"}
    again = runner.invoke(app, args)
    assert "0 upgraded, 1 already done, 1 failed" in again.output


def test_batch_upgrade_refuses_an_unknown_backend(tmp_path: Path) -> None:
    result = runner.invoke(app, ["batch-upgrade", str(tmp_path), str(tmp_path / "o"), "--backend", "nope"])
    assert result.exit_code == 2 and "error: unknown backend 'nope'" in result.output


def test_the_ray_backend_keeps_every_actor_busy(tmp_path: Path) -> None:
    """Two actors, two sequences in flight: both upgraded, the bad one reported, through the command."""
    ray = pytest.importorskip("ray")
    root = dataset(tmp_path / "amass")
    shutil.copy(DATA / "cmu_131_smpl.npz", root / "t" / "run.npz")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        result = runner.invoke(
            app,
            ["batch-upgrade", str(root), str(tmp_path / "out"), "--backend", "ray", "--concurrency", "2"],
            env={"BODYFIT_SMPL_MODEL": str(DATA / "smpl_like_model.npz")},
        )
    finally:
        ray.shutdown()
    assert result.exit_code == 1, result.output
    assert "2 upgraded, 0 already done, 1 failed" in result.output and "FAILED t/broken.npz" in result.output
    assert np.load(tmp_path / "out" / "t" / "run.npz")["coordinates"].shape == (60, 46)

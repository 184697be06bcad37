"""The command line's old module paths under bodyfit/clients keep working for one release: each is a shim
that re-exports the public names of the module that replaced it (the same objects) and says so in its
docstring, without a warning at import; ``python -m bodyfit.clients.cli`` still runs the command. The
in-process batch back-ends reached through :mod:`bodyfit.clients.batch` warn when used."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import pytest

MOVED = {
    "bodyfit.clients.cli": "bodyfit.cli.app",
    "bodyfit.clients.marker_cli": "bodyfit.cli.fit.markers",
    "bodyfit.clients.mesh_cli": "bodyfit.cli.fit.scan",
    "bodyfit.clients.sequence_cli": "bodyfit.cli.fit.sequence",
}


@pytest.mark.parametrize(("old", "new"), MOVED.items(), ids=list(MOVED))
def test_an_old_path_re_exports_the_new_modules_names(old: str, new: str) -> None:
    shim, module = importlib.import_module(old), importlib.import_module(new)
    doc = " ".join((shim.__doc__ or "").split())
    assert f"Deprecated: moved to :mod:`{new}`" in doc
    assert "will be removed in the next release" in doc
    assert shim.__all__, old
    for name in shim.__all__:
        assert getattr(shim, name) is getattr(module, name), f"{old}.{name}"


def test_the_old_app_is_the_bodyfit_command() -> None:
    from bodyfit.cli import app
    from bodyfit.clients.cli import app as old

    assert old is app


def test_the_old_paths_import_without_a_warning() -> None:
    code = "import importlib, sys\nfor m in sys.argv[1:]: importlib.import_module(m)\n"
    done = subprocess.run(
        [sys.executable, "-W", "error", "-c", code, *MOVED], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stderr == ""


def test_the_old_module_still_runs_the_command() -> None:
    for module in ("bodyfit.clients.cli", "bodyfit.cli"):
        done = subprocess.run(
            [sys.executable, "-m", module, "fit", "--help"], capture_output=True, text=True, timeout=120
        )
        assert done.returncode == 0, done.stderr[-2000:]
        assert "markers" in done.stdout and "sequence" in done.stdout, module


def test_the_local_upgrader_moved_with_a_deprecated_path() -> None:
    from bodyfit.cli.backends import LocalUpgrader
    from bodyfit.clients import batch

    assert batch.LocalUpgrader is LocalUpgrader
    with pytest.raises(AttributeError, match="no attribute 'Nothing'"):
        _ = batch.Nothing


def test_an_in_process_backend_named_to_the_sdk_warns(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``batch_upgrade(backend="local")`` still runs, through :func:`bodyfit.cli.backends.upgrader`, with a
    DeprecationWarning that names the replacement (the back-end is stubbed: the routing is tested)."""
    import bodyfit.cli.backends
    from bodyfit.clients.batch import batch_upgrade

    asked: list[tuple[str, int, object]] = []

    def upgrader(backend: str, concurrency: int = 1, smpl_model: object = None) -> object:
        asked.append((backend, concurrency, smpl_model))
        return lambda path: {"json": b"{}"}

    monkeypatch.setattr(bodyfit.cli.backends, "upgrader", upgrader)
    root = tmp_path / "data"
    root.mkdir()
    (root / "a.npz").write_bytes(b"")
    with pytest.warns(DeprecationWarning, match=r"bodyfit\.cli\.backends\.upgrader"):
        report = batch_upgrade(root, tmp_path / "out", 3, "local", "model.npz", progress=False)
    assert asked == [("local", 3, "model.npz")] and report.done == ["a.npz"]

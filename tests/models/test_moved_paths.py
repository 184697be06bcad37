"""The old module paths of the fitting code and the file readers keep working for one release: each is a
shim that re-exports the public names of the module that replaced it (the same objects, so isinstance checks
and pickles agree) and says so in its docstring, without a warning at import."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest

MOVED = {
    "bodyfit.models.fitting.lbfgs": "bodyfit.models.fitting.common.lbfgs",
    "bodyfit.models.fitting.report": "bodyfit.models.fitting.common.report",
    "bodyfit.models.fitting.surface": "bodyfit.models.fitting.common.surface",
    "bodyfit.models.fitting.nearest": "bodyfit.models.fitting.common.nearest",
    "bodyfit.models.fitting.nonrigid": "bodyfit.models.fitting.common.nonrigid",
    "bodyfit.models.fitting.registered": "bodyfit.models.fitting.registered.fitter",
    "bodyfit.models.fitting.smpl_topology": "bodyfit.models.fitting.registered.smpl_topology",
    "bodyfit.models.fitting.scan_fit": "bodyfit.models.fitting.scan.fitter",
    "bodyfit.models.fitting.scan_config": "bodyfit.models.fitting.scan.config",
    "bodyfit.models.fitting.scan_helper": "bodyfit.models.fitting.scan.helper",
    "bodyfit.models.fitting.limb_search": "bodyfit.models.fitting.scan.limb_search",
    "bodyfit.models.fitting.view": "bodyfit.models.fitting.scan.view",
    "bodyfit.models.fitting.sequence": "bodyfit.models.fitting.sequence.fitter",
    "bodyfit.models.fitting.offsets": "bodyfit.models.fitting.sequence.offsets",
    "bodyfit.models.fitting.retarget": "bodyfit.models.fitting.retarget.fitter",
    "bodyfit.models.fitting.markers": "bodyfit.models.fitting.mocap.fitter",
    "bodyfit.models.fitting.marker_ik": "bodyfit.models.fitting.mocap.marker_ik",
    "bodyfit.models.fitting.marker_solve": "bodyfit.models.fitting.mocap.marker_solve",
    "bodyfit.models.fitting.marker_sets": "bodyfit.models.fitting.mocap.marker_sets",
    "bodyfit.models.fitting.calibration": "bodyfit.models.fitting.mocap.calibration",
    "bodyfit.models.fitting.subject": "bodyfit.models.fitting.mocap.subject",
    "bodyfit.models.fitting.scan_io": "bodyfit.io.scans",
    "bodyfit.models.fitting.pcd": "bodyfit.io.pcd",
    "bodyfit.models.fitting.c3d": "bodyfit.io.c3d",
    "bodyfit.models.fitting.mocap_io": "bodyfit.io.mocap",
    "bodyfit.models.fitting.bvh": "bodyfit.io.bvh",
    "bodyfit.models.upgrade.smpl_io": "bodyfit.io.smpl",
}


@pytest.mark.parametrize(("old", "new"), MOVED.items(), ids=list(MOVED))
def test_an_old_path_re_exports_the_new_modules_names(old: str, new: str) -> None:
    shim, module = importlib.import_module(old), importlib.import_module(new)
    doc = " ".join((shim.__doc__ or "").split())
    assert f"Deprecated: moved to :mod:`{new}`" in doc or f"Deprecated: the module ``{old}`` moved to" in doc
    assert "will be removed in the next release" in doc
    assert shim.__all__, old
    for name in shim.__all__:
        assert getattr(shim, name) is getattr(module, name), f"{old}.{name}"


def test_the_old_paths_import_without_a_warning() -> None:
    code = "import importlib, sys\nfor m in sys.argv[1:]: importlib.import_module(m)\n"
    done = subprocess.run(
        [sys.executable, "-W", "error", "-c", code, *MOVED], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stderr == ""


def test_the_moved_readers_import_no_torch_web_or_grpc() -> None:
    """The file formats that moved to :mod:`bodyfit.io` stay importable without the server's dependencies."""
    readers = [f"bodyfit.io.{m}" for m in ("scans", "pcd", "c3d", "mocap", "bvh", "smpl")]
    code = (
        "import importlib, sys\n"
        "for m in sys.argv[1:]: importlib.import_module(m)\n"
        "print(sorted({'torch', 'fastapi', 'grpc'} & set(sys.modules)))\n"
    )
    done = subprocess.run([sys.executable, "-c", code, *readers], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "[]"

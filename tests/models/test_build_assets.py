"""`bodyfit build-assets --quick`: every build step runs on a small population and produces loadable assets.

This is the CI-sized build (a fresh clone first builds anny's cache: about 1.5 minutes)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from bodyfit.models.assets import read_manifest, sha256
from bodyfit.models.body.build import BuildConfig
from bodyfit.models.body.model import BodyModel


@pytest.fixture(scope="module")
def quick_assets(tmp_path_factory: pytest.TempPathFactory) -> Path:
    pytest.importorskip("anny")
    from bodyfit.models.build_assets import build_all

    out = tmp_path_factory.mktemp("assets")
    lines: list[str] = []
    build_all(out, out / "docs", log=lines.append, config=BuildConfig.quick())
    assert any("skinning" in line for line in lines)
    return out


@pytest.mark.build
def test_quick_build_writes_hashed_assets_with_metrics(quick_assets: Path) -> None:
    manifest = read_manifest(quick_assets)
    files = manifest["files"]
    for name in ("skeleton.json", "bones.npz", "body.npz", "body.onnx"):
        assert sha256(quick_assets / name) == files[name]["sha256"]
    m = files["body.npz"]["metrics"]
    assert m["population"] == {"bodies": 120, "held_out": 12, "children": False}
    assert len(m["bone_pca_explained"]) == BuildConfig.quick().n_bone
    assert 0.5 < sum(m["bone_pca_explained"]) <= 1.0
    # Reconstruction improves with every coefficient added, and the skinning refinement helps.
    curve = [row["ours_mean"] for row in m["heldout_reconstruction_mm"]]
    assert curve == sorted(curve, reverse=True) and curve[-1] < 2.0
    assert m["skinning_heldout_mm"]["after_mean"] < m["skinning_heldout_mm"]["before_mean"]
    assert max(v["mean"] for v in m["joint_regressor_heldout_mm"].values()) < 20.0
    assert max(v["mean"] for v in m["skeleton_fit_mm"].values()) < 15.0


@pytest.mark.build
def test_quick_build_model_loads_and_is_symmetric_at_the_template(quick_assets: Path) -> None:
    body = BodyModel.load(quick_assets)
    out = body.forward(dtype=torch.float64)
    v = out.vertices[0].numpy()
    assert np.abs(v - v[body.data["mirror"]] * np.array([1.0, 1.0, -1.0])).max() < 1e-6
    assert np.allclose(body.data["weights"].sum(axis=1), 1.0, atol=1e-5)
    assert (body.data["weights"] >= 0).all() and (body.data["joint_regressor"] >= 0).all()

"""A rig built by the service: raw scans reach the rig's closest-point refinement with their own points,
meshes in our topology do not."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch

from bodyfit.io.scans import scan_from_arrays
from bodyfit.service import subjects
from bodyfit.service.core import BodyService


def test_raw_scans_points_reach_the_rig(body_service: BodyService, monkeypatch: pytest.MonkeyPatch) -> None:
    model = body_service.model
    q = np.zeros((3, len(model.dof_names)))
    with torch.no_grad():
        meshes = model.forward(np.zeros((3, model.n_shape)), q, dtype=torch.float64).vertices.numpy()
    cloud = meshes[1, ::3] + np.array([0.0, 0.0, 0.5])  # a raw point cloud: not our vertex count
    scans = [scan_from_arrays(meshes[0], model.faces), scan_from_arrays(cloud), scan_from_arrays(meshes[2])]
    seen: dict[str, Any] = {}

    def fake_registrations(*args: Any) -> np.ndarray:
        return meshes

    def fake_build(model_: Any, x: np.ndarray, names: Any, config: Any = None, points: Any = None) -> str:
        seen["x"], seen["points"] = x, points
        return "built"

    monkeypatch.setattr(subjects, "registrations", fake_registrations)
    monkeypatch.setattr(subjects, "build_rig", fake_build)
    assert subjects.build_subject(body_service, scans, ["a", "b", "c"]) == "built"
    assert seen["points"][0] is None and seen["points"][2] is None
    np.testing.assert_array_equal(seen["points"][1], cloud)

"""The public Skeleton API: bad input, the bounded parameterisation, splines, assets and generated docs."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from bodyfit.models.assets import verified_asset
from bodyfit.models.errors import (
    AssetError,
    CoordinateRangeError,
    NonFiniteError,
    ShapeError,
    UnknownCoordinateError,
)
from bodyfit.models.skeleton import Skeleton, SkeletonSpec
from bodyfit.models.skeleton.docs import skeleton_markdown
from bodyfit.models.skeleton.functions import evaluate_function, fmm_spline_second_derivatives
from bodyfit.models.skeleton.spec import Function
from tests.conftest import random_pose

REPO = Path(__file__).resolve().parents[2]


# --- the skeleton's make-up -------------------------------------------------------------------------------
def test_dof_count_and_names(skeleton: Skeleton) -> None:
    assert skeleton.n_dof == 46
    rajagopal = [c.name for c in skeleton.spec.coordinates if c.rajagopal]
    assert len(rajagopal) == 34 and "knee_angle_r" in rajagopal and "knee_angle_r_beta" not in rajagopal
    for stem in ("thorax", "neck"):
        assert {f"{stem}_extension", f"{stem}_bending", f"{stem}_rotation"} <= set(skeleton.dof_names)
    for side in "rl":
        for stem in ("scapula_abduction", "scapula_elevation", "scapula_upward_rot", "pro_sup", "wrist_flex"):
            assert f"{stem}_{side}" in skeleton.dof_names
    assert [c.name for c in skeleton.spec.root_coordinates] == ["pelvis_tx", "pelvis_ty", "pelvis_tz"]


def test_limits_are_symmetric_and_unlocked_ranges_come_from_literature(skeleton: Skeleton) -> None:
    for c in skeleton.spec.coordinates:
        assert c.range[0] < c.range[1] and c.range_source
        if c.name.endswith("_r"):
            twin = skeleton.spec.coordinate(c.name[:-2] + "_l")
            assert twin.range == pytest.approx(c.range)
    for name in ("subtalar_angle_r", "mtp_angle_r", "wrist_flex_r", "wrist_dev_r"):
        assert "unlocked" in skeleton.spec.coordinate(name).range_source


# --- bad input --------------------------------------------------------------------------------------------
def test_wrong_shape_is_a_shape_error(skeleton: Skeleton) -> None:
    with pytest.raises(ShapeError, match=r"\(B, 46\)"):
        skeleton.forward(np.zeros((2, 45)))
    with pytest.raises(ShapeError, match="root translation"):
        skeleton.forward(np.zeros((2, 46)), root=np.zeros((2, 2)))
    with pytest.raises(ShapeError, match="scale factors"):
        skeleton.forward(np.zeros((2, 46)), scales=np.ones((2, 3)))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_values_are_refused(skeleton: Skeleton, bad: float) -> None:
    q = np.zeros((3, skeleton.n_dof))
    q[1, 7] = bad
    with pytest.raises(NonFiniteError, match=r"index \[1, 7\]"):
        skeleton.forward(q)
    with pytest.raises(NonFiniteError, match="root"):
        skeleton.forward(np.zeros((1, 46)), root=np.array([[0.0, bad, 0.0]]))


def test_unknown_coordinate_names_suggest_the_fix(skeleton: Skeleton) -> None:
    with pytest.raises(UnknownCoordinateError, match="Did you mean knee_angle_r"):
        skeleton.coordinates({"knee_angle_rr": 0.3})
    with pytest.raises(UnknownCoordinateError, match="unknown coordinate 'elbow'"):
        skeleton.dof_index("elbow")


def test_out_of_range_is_an_error_never_clamped(skeleton: Skeleton) -> None:
    q = skeleton.coordinates({"knee_angle_r": -0.2})
    with pytest.raises(CoordinateRangeError, match=r"knee_angle_r=-0\.2 rad \(range 0\.\.2\.094\)"):
        skeleton.forward(q)
    with pytest.raises(CoordinateRangeError, match="positive"):
        skeleton.forward(np.zeros((1, 46)), scales=np.zeros((1, len(skeleton.segments), 3)))


def test_named_coordinates_fill_the_rest_with_zero(skeleton: Skeleton) -> None:
    q = skeleton.coordinates({"knee_angle_l": np.array([0.1, 0.2]), "hip_flexion_r": 0.5})
    assert q.shape == (2, 46)
    assert q[:, skeleton.dof_index("knee_angle_l")].tolist() == [0.1, 0.2]
    assert q[:, skeleton.dof_index("hip_flexion_r")].tolist() == [0.5, 0.5]
    assert np.count_nonzero(q) == 4


# --- bounded parameterisation ----------------------------------------------------------------------------
def test_unbounded_values_always_land_inside_the_ranges(skeleton: Skeleton) -> None:
    u = torch.randn(1000, skeleton.n_dof, dtype=torch.float64) * 20  # many saturate
    q = skeleton.from_unbounded(u)
    lo, hi = torch.tensor(skeleton.ranges[:, 0]), torch.tensor(skeleton.ranges[:, 1])
    assert bool(((q >= lo - 1e-12) & (q <= hi + 1e-12)).all())  # saturated tanh: within rounding
    skeleton.forward(q)  # valid input


def test_bounded_round_trip(skeleton: Skeleton) -> None:
    q = torch.tensor(random_pose(skeleton, 200, seed=30))
    assert torch.allclose(skeleton.from_unbounded(skeleton.to_unbounded(q)), q, atol=1e-9)
    u = torch.randn(50, skeleton.n_dof, dtype=torch.float64)
    assert torch.allclose(skeleton.to_unbounded(skeleton.from_unbounded(u)), u, atol=1e-9)
    mid = torch.tensor(skeleton.ranges.mean(1))
    assert torch.allclose(skeleton.from_unbounded(torch.zeros(1, skeleton.n_dof, dtype=torch.float64)), mid)
    with pytest.raises(CoordinateRangeError):
        skeleton.to_unbounded(torch.full((1, skeleton.n_dof), 10.0, dtype=torch.float64))


# --- splines (OpenSim SimmSpline) -----------------------------------------------------------------------
def test_simm_spline_reproduces_cubic_data_exactly() -> None:
    """The Forsythe-Malcolm-Moler end conditions make the spline exact for cubic data; a natural spline
    would not be (its ends have zero curvature)."""
    x = np.array([0.0, 0.3, 0.5, 1.1, 1.4, 2.0])
    cubic = 0.2 - 0.5 * x + 0.7 * x**2 - 0.3 * x**3
    fn = Function("spline", {"x": x.tolist(), "y": cubic.tolist()})
    xs = np.linspace(0, 2, 41)
    assert np.allclose(evaluate_function(fn, xs), 0.2 - 0.5 * xs + 0.7 * xs**2 - 0.3 * xs**3, atol=1e-12)
    assert not np.allclose(fmm_spline_second_derivatives(x, cubic)[[0, -1]], 0.0)


def test_simm_spline_extrapolates_linearly() -> None:
    x = [0.0, 1.0, 2.0, 3.0]
    fn = Function("spline", {"x": x, "y": [0.0, 1.0, 0.0, 2.0]})
    inside = evaluate_function(fn, np.array([2.999999, 3.0]))
    slope = (inside[1] - inside[0]) / 1e-6
    far = evaluate_function(fn, np.array([4.0, 5.0]))
    assert far[1] - far[0] == pytest.approx(slope, rel=1e-4)
    assert far[0] - inside[1] == pytest.approx(slope, rel=1e-4)


# --- assets and docs ---------------------------------------------------------------------------------------
def test_manifest_hash_matches_the_asset() -> None:
    path = verified_asset("skeleton.json")
    assert SkeletonSpec.load(path).dof_names == Skeleton.load().dof_names


def test_corrupted_or_missing_asset_fails_with_rebuild_hint(tmp_path: Path) -> None:
    folder = tmp_path / "assets"
    shutil.copytree(REPO / "assets", folder)
    with (folder / "skeleton.json").open("a") as f:
        f.write(" ")
    with pytest.raises(AssetError, match=r"corrupted or stale.*bodyfit build-assets"):
        Skeleton.load(folder)
    (folder / "skeleton.json").unlink()
    with pytest.raises(AssetError, match=r"missing.*bodyfit build-assets"):
        Skeleton.load(folder)
    (folder / "manifest.json").write_text("{not json")
    with pytest.raises(AssetError, match="not valid JSON"):
        Skeleton.load(folder)


def test_docs_table_is_generated_from_the_asset(skeleton: Skeleton) -> None:
    text = (REPO / "docs" / "skeleton.md").read_text()
    assert text == skeleton_markdown(skeleton.spec), "docs/skeleton.md is stale: run `bodyfit build-assets`"
    rows = [line for line in text.splitlines() if line.startswith("| `")]
    assert len(rows) == skeleton.n_dof


def _same_up_to_rounding(built: object, stored: object, path: str = "spec") -> None:
    """The same structure, names and integers; floats equal to the last few bits (numpy builds differ in
    the last bit of sqrt and trigonometry)."""
    if isinstance(built, dict):
        assert isinstance(stored, dict) and built.keys() == stored.keys(), path
        for key in built:
            _same_up_to_rounding(built[key], stored[key], f"{path}/{key}")
    elif isinstance(built, list):
        assert isinstance(stored, list) and len(built) == len(stored), path
        for i, (a, b) in enumerate(zip(built, stored, strict=True)):
            _same_up_to_rounding(a, b, f"{path}[{i}]")
    elif isinstance(built, float):
        assert isinstance(stored, float | int) and abs(built - stored) <= 1e-12 * max(1.0, abs(stored)), path
    else:
        assert built == stored, path


@pytest.mark.opensim
def test_asset_rebuilds_identically_from_the_wheel(skeleton: Skeleton) -> None:
    pytest.importorskip("opensim")
    from bodyfit.models.skeleton.build import build_skeleton

    _same_up_to_rounding(build_skeleton().to_json(), skeleton.spec.to_json())
    with pytest.raises(AssertionError, match="joints"):  # and a real difference is caught
        changed = skeleton.spec.to_json()
        changed["joints"][18]["translations"][0]["function"]["offset"] += 1e-9
        _same_up_to_rounding(build_skeleton().to_json(), changed)

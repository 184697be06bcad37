"""A scan fit's hints in the service core: checked once for every transport (the error names the hint and
its allowed values), turned into the fitters' orientation and start pose, reported with how each was used;
and every route's answer in the input's frame with ``to_model`` alongside."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from bodyfit.io.scans import Scan, sample_surface
from bodyfit.models.fitting.common.surface import point_to_surface
from bodyfit.models.fitting.registered.smpl_topology import SMPL_TO_BODY, SOURCE_DIR, read_obj
from bodyfit.service.core import BodyService, SynthRequest
from bodyfit.service.errors import InvalidInputError
from bodyfit.service.hints import POSE_DEGREES, ScanHints, standing_height


@pytest.mark.parametrize(
    ("fields", "field", "words"),
    [
        ({"up": "upwards"}, "up", "up must be one of +x, -x, +y, -y, +z, -z"),
        ({"up": "+y", "facing": "front"}, "facing", "facing must be one of +x, -x, +y, -y, +z, -z"),
        ({"up": "+y", "facing": "-y"}, "facing", "perpendicular to up"),
        ({"pose": "kneeling"}, "pose", "pose must be one of standing, sitting, a-pose, t-pose"),
        ({"sex": "other"}, "sex", "sex must be one of male, female, neutral"),
        ({"height_m": 1750.0}, "height_m", "between 1.2 and 2.3"),
        ({"height_m": float("nan")}, "height_m", "between 1.2 and 2.3"),
    ],
)
def test_a_bad_hint_names_itself_and_its_allowed_values(
    fields: dict[str, object], field: str, words: str
) -> None:
    with pytest.raises(InvalidInputError, match=words.replace("+", r"\+")) as err:
        ScanHints.given(**fields)  # type: ignore[arg-type]
    assert err.value.field == field


def test_hints_are_spelled_one_way_and_give_a_rotation() -> None:
    hints = ScanHints.given("Z", "-x", "A-Pose", "", None)
    assert (hints.up, hints.facing, hints.pose, hints.sex) == ("+z", "-x", "a-pose", None)
    assert hints.given_names() == ["up", "facing", "pose"]
    R = hints.orientation()
    assert R is not None and np.isclose(np.linalg.det(R), 1.0)
    np.testing.assert_allclose(R @ [0, 0, 1], [0, 1, 0])  # the scan's up is the body's +Y
    np.testing.assert_allclose(R @ [-1, 0, 0], [1, 0, 0])  # the way the person faces is the body's +X
    assert ScanHints.given(up="+z").orientation() is None  # one axis does not fix an orientation


def test_every_pose_class_starts_inside_the_limits(body_service: BodyService) -> None:
    model = body_service.model
    skel = model.skeleton
    for name, degrees in POSE_DEGREES.items():
        q = ScanHints(pose=name).start(model)  # type: ignore[arg-type]
        if not degrees:
            assert q is None  # standing: the fitters' own start
            continue
        assert q is not None and np.all((q >= skel.ranges[:, 0]) & (q <= skel.ranges[:, 1]))
        for dof, value in degrees.items():
            assert q[skel.dof_index(dof)] == pytest.approx(np.radians(value))
    assert 1.5 < standing_height(model, np.zeros(model.n_shape)) < 1.9


def _scan_of(service: BodyService, points: np.ndarray) -> Scan:
    buf = io.BytesIO()
    np.savez(buf, points=points)
    return service.read_scan(buf.getvalue(), "npz")


def _mesh_of(service: BodyService, verts: np.ndarray, faces: np.ndarray) -> Scan:
    import trimesh

    data = trimesh.Trimesh(verts, faces, process=False).export(file_type="ply")
    assert isinstance(data, bytes)
    return service.read_scan(data, "ply", "m")


def test_a_raw_scan_uses_the_orientation_pose_and_height_hints(body_service: BodyService) -> None:
    """A seated body scanned lying along -X with +Z up in its own frame: the orientation and the pose class
    are used (not searched: no searched-orientation reason), the height is checked, sex is recorded; the
    registration lies on the scan and to_model maps the fit's frame to the parameters'."""
    model = body_service.model
    q = ScanHints(pose="sitting").start(model)
    assert q is not None
    body = body_service.synthesize(SynthRequest(coordinates=q[None])).vertices[0].astype(np.float64)
    points, _ = sample_surface(body, model.faces, 20_000, seed=7)
    R = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # body forward -> +y, up -> +z
    t = np.array([1.0, 0.5, -0.2])
    hints = ScanHints.given("+z", "+y", "sitting", "female", standing_height(model, np.zeros(model.n_shape)))
    fit = body_service.fit_mesh(_scan_of(body_service, points @ R.T + t), hints=hints)
    assert fit.fitted_as == "raw scan"
    moved = body @ R.T + t
    assert point_to_surface(fit.vertices, moved, model.faces).mean() < 0.005
    report = fit.report
    used = {name: h["used"] for name, h in report.extra["hints"].items()}
    assert used == {"up": True, "facing": True, "pose": True, "sex": False, "height_m": True}
    assert report.extra["hints"]["height_m"]["how"].startswith("checked: the fitted body stands")
    assert not any("orientation was searched" in r for r in report.reasons)
    assert report.confident, report.reasons
    assert report.scan_to_model is not None and report.model_to_scan is not None
    assert report.model_to_scan.mean < 6.0
    S = fit.to_model
    with torch.no_grad():
        posed = model.forward(fit.shape[None], fit.coordinates[None], fit.root[None], dtype=torch.float64)
    placed = posed.vertices[0].numpy() @ S[:3, :3] - S[:3, 3] @ S[:3, :3]  # back into the scan's frame
    assert point_to_surface(placed, moved, model.faces).mean() < 0.01

    wrong = ScanHints.given(height_m=2.2)
    again = body_service.fit_mesh(_scan_of(body_service, points @ R.T + t), hints=wrong)
    assert not again.report.confident
    assert any("height hint says 2.20 m" in r for r in again.report.reasons)


def test_up_alone_keeps_the_search_about_that_axis(body_service: BodyService) -> None:
    """A standing body scanned with +Z up and an unknown heading: with up alone the search tries headings
    about +Z only, and the fit lies on the scan; the report says up was used and the heading searched."""
    model = body_service.model
    body = body_service.synthesize(SynthRequest()).vertices[0].astype(np.float64)
    points, _ = sample_surface(body, model.faces, 20_000, seed=3)
    a = 0.7  # a heading none of the candidates has exactly
    R = np.array([[np.cos(a), 0.0, -np.sin(a)], [np.sin(a), 0.0, np.cos(a)], [0.0, 1.0, 0.0]])  # up -> +z
    assert np.allclose(R @ np.array([0.0, 1.0, 0.0]), [0.0, 0.0, 1.0])
    fit = body_service.fit_mesh(_scan_of(body_service, points @ R.T), hints=ScanHints.given("+z"))
    assert point_to_surface(fit.vertices, body @ R.T, model.faces).mean() < 0.005
    up = fit.report.extra["hints"]["up"]
    assert up["used"] and "headings about this up axis" in up["how"]
    assert any("orientation was searched" in r for r in fit.report.extra["observations"])


def test_an_smpl_topology_mesh_answers_in_its_own_frame(body_service: BodyService) -> None:
    """The CC BY body as it comes (SMPL's +Y up, facing +Z): the registration lies on it, not 90 degrees
    away in our frame, and to_model is SMPL's turn into ours; the same body turned to +Z up and facing +X is
    placed by its up and facing hints, which the report says were used."""
    verts, faces = read_obj(SOURCE_DIR / "human_woman.obj")
    fit = body_service.fit_mesh(_mesh_of(body_service, verts, faces))
    assert fit.fitted_as == "SMPL topology"
    assert point_to_surface(fit.vertices, verts, faces).mean() < 0.005
    np.testing.assert_allclose(fit.to_model[:3, :3], SMPL_TO_BODY, atol=1e-9)

    axes = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # SMPL's +Y -> +Z, +Z -> +X
    moved = verts @ axes.T + np.array([0.0, 2.0, 0.3])
    turned = body_service.fit_mesh(
        _mesh_of(body_service, moved, faces), hints=ScanHints.given(up="+z", facing="+x")
    )
    assert point_to_surface(turned.vertices, moved, faces).mean() < 0.005
    assert turned.report.extra["hints"]["up"]["used"] is True and turned.report.predicted_error_mm is not None


def test_a_registered_mesh_records_the_hints_it_needs_not(body_service: BodyService) -> None:
    model = body_service.model
    body = body_service.synthesize(SynthRequest()).vertices[0].astype(np.float64)
    moved = body @ np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]).T + np.array(
        [0.4, 0.0, 1.0]
    )
    fit = body_service.fit_mesh(_scan_of(body_service, moved), hints=ScanHints.given("+x", "+y", "t-pose"))
    assert fit.fitted_as == "registered" and np.linalg.norm(fit.vertices - moved, axis=1).mean() < 0.003
    np.testing.assert_array_equal(fit.to_model, np.eye(4))
    hints = fit.report.extra["hints"]
    assert {h["used"] for h in hints.values()} == {False} and hints["up"]["how"].startswith("recorded")
    assert model.n_vertices == len(fit.vertices)

"""One frame convention for every mesh fit: the registration and joints lie on the input as it was given, and
the map to the frame the parameters pose the model in comes alongside (``scan_to_body``), for SMPL-topology
meshes (the CC BY bodies of data/smpl_ccby, in SMPL's frame or turned and moved), registered meshes and raw
scans."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from bodyfit.io.scans import sample_surface
from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common.surface import point_to_surface
from bodyfit.models.fitting.registered.fitter import RegisteredFitter
from bodyfit.models.fitting.registered.smpl_topology import SMPL_TO_BODY, SOURCE_DIR, fit_smpl_mesh, read_obj
from bodyfit.models.fitting.scan.fitter import ScanFit, ScanFitter
from bodyfit.models.rotations import zxy_angles


@pytest.fixture(scope="module")
def model() -> BodyModel:
    return BodyModel.load()


@pytest.fixture(scope="module")
def registered(model: BodyModel) -> RegisteredFitter:
    return RegisteredFitter(model)


def _posed(model: BodyModel, shape: np.ndarray, q: np.ndarray, root: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        out = model.forward(shape[None], q[None], root[None], dtype=torch.float64)
    return out.vertices[0].numpy()


def _turn(angle: float, axis: np.ndarray) -> np.ndarray:
    """(3, 3) the rotation by ``angle`` (rad) about the unit ``axis`` (Rodrigues)."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _check_convention(model: BodyModel, fit: ScanFit, mesh: np.ndarray, faces: np.ndarray) -> float:
    """The fit's registration lies on ``mesh`` (returns the mean distance, mm) and its parameters pose the
    body where ``scan_to_body`` (rigid) maps its parametric vertices."""
    S = fit.scan_to_body
    body = _posed(model, fit.shape, fit.coordinates, fit.root)
    np.testing.assert_allclose(body, fit.vertices @ S[:3, :3].T + S[:3, 3], atol=1e-5)
    np.testing.assert_allclose(S[:3, :3] @ S[:3, :3].T, np.eye(3), atol=1e-9)
    return float(point_to_surface(fit.registration, mesh, faces).mean() * 1000)


def test_smpl_topology_meshes_answer_in_their_own_frame(
    model: BodyModel, registered: RegisteredFitter
) -> None:
    """The CC BY bodies in SMPL's frame (+Y up, facing +Z), and one turned to +Z up, facing +X and moved 2 m
    with that orientation given: the registration lies on the mesh as it came (a few mm), never in our
    frame, 90 degrees away."""
    scanner = ScanFitter(model, fitter=registered)
    verts, faces = read_obj(SOURCE_DIR / "human_man.obj")
    fit = fit_smpl_mesh(registered, scanner, verts, faces)
    assert _check_convention(model, fit, verts, faces) < 5.0
    np.testing.assert_allclose(fit.scan_to_body[:3, :3], SMPL_TO_BODY, atol=1e-9)
    in_our_frame = verts @ SMPL_TO_BODY.T
    assert point_to_surface(fit.registration, in_our_frame, faces).mean() * 1000 > 50.0
    assert fit.joints[:, 1].max() - fit.joints[:, 1].min() > 1.0  # the joints stand along the mesh's +Y

    verts, faces = read_obj(SOURCE_DIR / "human_woman.obj")
    axes = np.array(
        [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    )  # SMPL's +Y up -> +Z, +Z facing -> +X
    moved = verts @ axes.T + np.array([0.5, -1.0, 2.0])
    to_body = SMPL_TO_BODY @ axes.T
    turned = fit_smpl_mesh(registered, scanner, moved, faces, to_body)
    assert _check_convention(model, turned, moved, faces) < 5.0
    assert turned.joints[:, 2].max() - turned.joints[:, 2].min() > 1.0  # now along +Z
    # a real body outside the population: its registration error is predicted, not taken on trust
    assert turned.report.predicted_error_mm is not None and turned.report.limit_violations == 0


def test_registered_meshes_answer_in_their_own_frame(model: BodyModel, registered: RegisteredFitter) -> None:
    """A body of our topology turned 70 degrees about a tilted axis and moved: the registered fit lies on
    it; its parameters hold the placement themselves (the convention's identity map)."""
    skel = model.skeleton
    q = skel.coordinates({"knee_angle_r": 0.7, "hip_flexion_l": 0.5, "elbow_flex_r": 1.1})[0]
    R = _turn(np.radians(70.0), np.array([0.3, 0.8, 0.5]) / np.linalg.norm([0.3, 0.8, 0.5]))
    q[[skel.dof_index(n) for n in ("pelvis_tilt", "pelvis_list", "pelvis_rotation")]] = zxy_angles(R)
    body = _posed(model, np.zeros(model.n_shape), q, np.array([1.5, 0.4, -2.0]))
    fit = registered.fit(body[None])
    assert np.linalg.norm(fit.vertices[0] - body, axis=1).mean() * 1000 < 3.0
    np.testing.assert_allclose(
        _posed(model, fit.shape[0], fit.coordinates[0], fit.root[0]), fit.vertices[0], atol=1e-5
    )


def test_a_raw_scan_upside_down_answers_in_its_own_frame(
    model: BodyModel, registered: RegisteredFitter
) -> None:
    """A body scanned upside down and moved, its orientation given: the registration lies on the scan and
    the parameters pose the body where ``scan_to_body`` maps the fit's vertices."""
    skel = model.skeleton
    q = skel.inside(model.bind_coordinates, 0.1)
    body = _posed(model, np.zeros(model.n_shape), q, np.zeros(3))
    faces = np.asarray(model.faces, np.int64)
    points, _ = sample_surface(body, faces, 20_000, seed=5)
    R = _turn(np.pi, np.array([1.0, 0.0, 0.0]))  # upside down
    scan = points @ R.T + np.array([0.3, 2.0, -1.0])
    fit = ScanFitter(model, fitter=registered).fit(scan, orientation=R.T)
    assert _check_convention(model, fit, body @ R.T + np.array([0.3, 2.0, -1.0]), faces) < 5.0
    assert fit.report.confident, fit.report.reasons

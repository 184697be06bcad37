"""The transport-neutral core: synthesis equals the torch model, errors name the field, jobs stop."""

from __future__ import annotations

import io
from typing import Any

import numpy as np
import pytest
import torch

from bodyfit.service.core import BodyService, SynthRequest
from bodyfit.service.errors import (
    DeadlineExceededError,
    InvalidInputError,
    JobCancelledError,
    LimitExceededError,
)
from bodyfit.service.formats import encode_bodies
from bodyfit.service.jobs import Job, Progress


def test_info_lists_every_dof_with_range_and_unit(body_service: BodyService) -> None:
    info = body_service.info()
    skel = body_service.model.skeleton
    assert info.dof_names == tuple(skel.dof_names) and info.dof_ranges.shape == (skel.n_dof, 2)
    assert info.dof_units == tuple(
        "m" if c.motion == "translational" else "rad" for c in skel.spec.coordinates
    )
    assert info.n_shape == body_service.model.n_shape and info.n_vertices == 13348
    assert all(len(h) == 64 for h in info.asset_sha256.values()) and "body.onnx" in info.asset_sha256


def test_onnx_synthesis_matches_the_torch_model(body_service: BodyService) -> None:
    rng = np.random.default_rng(0)
    model = body_service.model
    lo, hi = model.skeleton.ranges.T
    q = rng.uniform(lo * 0.5, hi * 0.5, (3, model.skeleton.n_dof))
    shape = rng.normal(size=(3, model.n_shape))
    root = rng.normal(size=(3, 3))
    bodies = body_service.synthesize(SynthRequest(shape, q, root, skeleton=True))
    with torch.no_grad():
        ref = model.forward(shape, q, root)
    assert np.abs(bodies.vertices - ref.vertices.numpy()).max() < 1e-5
    assert np.abs(bodies.joints - ref.joints.numpy()).max() < 1e-5
    assert bodies.bones is not None and bodies.bones.shape[0] == 3


def test_named_coordinates_and_batch(body_service: BodyService) -> None:
    bent = body_service.synthesize(SynthRequest(coordinates={"knee_angle_r": [0.0, 1.5]}))
    assert bent.batch == 2
    moved = np.linalg.norm(bent.vertices[1] - bent.vertices[0], axis=1)
    assert moved.max() > 0.2  # the right shank swings
    assert body_service.synthesize(SynthRequest(batch=3)).batch == 3


@pytest.mark.parametrize(
    ("request_", "field", "words"),
    [
        (SynthRequest(coordinates={"knee_angel_r": 1.0}), "coordinates", "knee_angle_r"),
        (SynthRequest(coordinates={"knee_angle_r": 5.0}), "coordinates", "range"),
        (SynthRequest(coordinates=np.zeros((1, 3))), "coordinates", "(B, 46)"),
        (SynthRequest(shape=np.zeros((1, 5))), "shape", "8 bone"),
        (SynthRequest(root=np.full((1, 3), np.nan)), "root", "NaN"),
        (SynthRequest(batch=0), "batch", "at least 1"),
    ],
)
def test_bad_synthesis_requests_name_the_field(
    body_service: BodyService, request_: SynthRequest, field: str, words: str
) -> None:
    with pytest.raises(InvalidInputError) as err:
        body_service.synthesize(request_)
    assert err.value.field == field and words in err.value.detail


def test_limits(body_service: BodyService) -> None:
    with pytest.raises(LimitExceededError, match="split"):
        body_service.synthesize(SynthRequest(batch=65))
    frames = np.zeros((body_service.limits.max_frames + 1, 3, 3))
    with pytest.raises(LimitExceededError):
        body_service.fit_sequence(frames)


def test_formats_hold_the_mesh(body_service: BodyService) -> None:
    import trimesh

    bodies = body_service.synthesize(SynthRequest())
    for fmt in ("ply", "obj"):
        mesh: Any = trimesh.load(io.BytesIO(encode_bodies(bodies, fmt)), file_type=fmt, process=False)
        assert np.allclose(mesh.vertices, bodies.vertices[0], atol=1e-5)
    scene: Any = trimesh.load(io.BytesIO(encode_bodies(bodies, "glb")), file_type="glb")
    assert sum(len(g.vertices) for g in scene.geometry.values()) == 13348
    with pytest.raises(InvalidInputError, match="one of"):
        encode_bodies(bodies, "fbx")


def test_fit_mesh_routes_and_recovers_the_pose(body_service: BodyService) -> None:
    q = body_service.model.skeleton.coordinates({"knee_angle_r": 0.8, "elbow_flex_l": 1.0})
    bodies = body_service.synthesize(SynthRequest(coordinates=q))
    buf = io.BytesIO()
    np.savez(buf, points=bodies.vertices[0])
    scan = body_service.read_scan(buf.getvalue(), "npz")
    events: list[str] = []
    fit = body_service.fit_mesh(scan, Job(on_progress=lambda p: events.append(p.message)))
    assert fit.fitted_as == "registered" and fit.report.distances.mean < 2.0
    knee = body_service.model.skeleton.dof_index("knee_angle_r")
    assert abs(fit.coordinates[knee] - 0.8) < 0.05
    assert events[0].endswith("points") and events[-1] == "done"


def test_a_scan_helper_process_gives_the_services_raw_scan_fit(body_service: BodyService) -> None:
    """``scan_processes=2`` (BODYFIT_SCAN_PROCESSES) gives the raw-scan fitter a helper process, and a raw
    scan's fit through the service is the one the service without it gives: both run with torch on the one
    thread the service set once at load, and no fit changes that setting."""
    from bodyfit.models.fitting.scan_io import sample_surface
    from bodyfit.service.limits import Limits

    q = body_service.model.skeleton.coordinates({"knee_angle_r": 0.8, "elbow_flex_l": 1.0})
    body = body_service.synthesize(SynthRequest(coordinates=q)).vertices[0]
    points, _ = sample_surface(body, body_service.model.faces, 20_000, seed=2)
    buf = io.BytesIO()
    np.savez(buf, points=points)
    scan = body_service.read_scan(buf.getvalue(), "npz")
    helped = BodyService.load(limits=Limits(queue_seconds=5.0), threads=1, scan_processes=2)
    scanner = helped.fitters.scan
    try:
        assert scanner.config.processes == 2 and scanner.wait_for_helper(180.0)
        assert scanner.fitter is helped.fitters.registered  # one registered fitter per service
        assert torch.get_num_threads() == 1  # set by the load, for the process
        fits = [helped.fit_mesh(scan)]
        events: list[Progress] = []
        fits.append(body_service.fit_mesh(scan, Job(on_progress=events.append)))
        assert torch.get_num_threads() == 1
        assert scanner.helper is not None and scanner.helper.completed == 3
    finally:
        scanner.close()
    assert [f.fitted_as for f in fits] == ["raw scan"] * 2
    # the service's start, the fit's own steps (the first says what it fits), then done
    assert [(p.done, p.total) for p in events] == [(0, 9), *((k, 9) for k in range(10)), (9, 9)]
    assert events[1].message.endswith("fitting a whole body") and events[-1].message == "done"
    np.testing.assert_array_equal(fits[0].coordinates, fits[1].coordinates)
    np.testing.assert_array_equal(fits[0].vertices, fits[1].vertices)


def test_a_head_and_shoulders_scan_reports_its_own_steps(body_service: BodyService) -> None:
    """A raw scan smaller than a body is fitted as a head and shoulders, in fewer steps than a whole body:
    the progress says so as soon as the fit knows and counts to that total (it used to jump to done)."""
    from bodyfit.models.fitting.scan_io import sample_surface

    body = body_service.synthesize(SynthRequest()).vertices[0]
    points, _ = sample_surface(body, body_service.model.faces, 30_000, seed=4)
    points = points[points[:, 1] > body[:, 1].max() - 0.45]
    buf = io.BytesIO()
    np.savez(buf, points=points)
    events: list[Progress] = []
    fit = body_service.fit_mesh(body_service.read_scan(buf.getvalue(), "npz"), Job(on_progress=events.append))
    assert fit.report.extra["fitted_part"] == "head and shoulders"
    n = len(body_service.fitters.scan.config.partial_phases)
    assert [(p.done, p.total) for p in events[1:]] == [*((k, n) for k in range(n + 1)), (n, n)]
    assert events[1].message.endswith("fitting a head and shoulders")


def test_cancelled_and_late_jobs_stop(body_service: BodyService) -> None:
    frames = body_service.synthesize(SynthRequest(batch=3)).vertices
    job = Job()
    job.cancel()
    with pytest.raises(JobCancelledError):
        body_service.fit_sequence(frames, job=job)
    with pytest.raises(DeadlineExceededError, match="BODYFIT_MAX_SECONDS"):
        body_service.fit_sequence(frames, job=Job(timeout_s=0.0))
    # The slot is released: the next job runs.
    assert len(body_service.fit_sequence(frames).coordinates) == 3


@pytest.mark.parametrize(
    ("data", "words"),
    [
        (b"not an npz", "not a readable .npz"),
        (b"", "not a readable .npz"),
    ],
)
def test_bad_sequence_uploads(body_service: BodyService, data: bytes, words: str) -> None:
    with pytest.raises(InvalidInputError, match=words):
        body_service.read_sequence(data)


def test_sequence_upload_needs_frames_of_our_topology(body_service: BodyService) -> None:
    for arrays, words in (
        ({"points": np.zeros((3, 3))}, "needs"),
        ({"frames": np.zeros((2, 10, 3))}, "(T, 13348, 3)"),
    ):
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        with pytest.raises(InvalidInputError) as err:
            body_service.read_sequence(buf.getvalue())
        assert words in err.value.detail and err.value.field == "frames"

"""The transport-neutral core: synthesis equals the torch model, errors name the field, jobs stop."""

from __future__ import annotations

import io
import zipfile
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
    sha256 = info.assets["sha256"]
    assert all(len(h) == 64 for h in sha256.values()) and "body.onnx" in sha256
    assert np.array_equal(info.dof_ranges, skel.ranges)


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
    from bodyfit.io.scans import sample_surface
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
    from bodyfit.io.scans import sample_surface

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


@pytest.mark.parametrize(
    ("request_", "field", "words"),
    [
        (SynthRequest(root=np.array([[0.0, 1e308, 0.0]])), "root", "[-100, 100]"),  # inf in float32
        (SynthRequest(root=np.array([[0.0, 150.0, 0.0]])), "root", "[-100, 100]"),
        (SynthRequest(shape=np.full((1, 32), 1e6)), "shape", "[-10, 10]"),
        (SynthRequest(shape=np.full((1, 32), 10.5)), "shape", "standard deviations"),
        (SynthRequest(coordinates=np.full((1, 46), 1e39)), "coordinates", "range"),
        (SynthRequest(shape=np.zeros((0, 32))), "shape", "0 bodies"),
        (SynthRequest(root=np.zeros((0, 3))), "root", "0 bodies"),
        (SynthRequest(coordinates=np.zeros((0, 46))), "coordinates", "0 bodies"),
        (SynthRequest(coordinates={"knee_angle_r": []}), "coordinates", "0 bodies"),
        (SynthRequest(root=np.zeros((1, 3), np.int32)), "root", "floats"),
        (SynthRequest(shape=np.zeros((1, 32), bool)), "shape", "floats"),
        (SynthRequest(coordinates=np.zeros((1, 46), np.int64)), "coordinates", "floats"),
    ],
)
def test_implausible_or_empty_synthesis_requests_are_refused(
    body_service: BodyService, request_: SynthRequest, field: str, words: str
) -> None:
    """Values that overflow float32, shapes beyond 10 SD, roots beyond 100 m, zero bodies and int / bool
    arrays: refused with the field and the range named, before any model call."""
    with pytest.raises(InvalidInputError) as err:
        body_service.synthesize(request_)
    assert err.value.field == field and words in err.value.detail, err.value.detail


def test_the_plausible_range_holds_the_extreme_adults(body_service: BodyService) -> None:
    """+-9.9 SD and a root 99 m away are accepted, and the bodies are finite."""
    shape = np.zeros((2, 32))
    shape[:, 0] = [-9.9, 9.9]
    bodies = body_service.synthesize(SynthRequest(shape=shape, root=np.array([[99.0, 0, -99.0]] * 2)))
    height = np.ptp(bodies.vertices[..., 1], axis=1)
    assert np.isfinite(bodies.vertices).all() and 0.6 < height[0] < 0.8 and 2.6 < height[1] < 2.8


def _bodies(service: BodyService, n: int = 2) -> np.ndarray:
    return service.synthesize(SynthRequest(batch=n)).vertices


def _flat(x: np.ndarray) -> np.ndarray:
    x = x.copy()
    x[..., 2] = 0.0
    return x


def _line(x: np.ndarray) -> np.ndarray:
    x = _flat(x)
    x[..., 0] = 0.0
    return x


def _overflow(x: np.ndarray) -> np.ndarray:
    x = x.astype(np.float64)
    x[1, 7, 0] = 1e308  # finite in float64, infinite in float32
    return x


def _nan(x: np.ndarray) -> np.ndarray:
    x = x.copy()
    x[1, 3] = np.nan
    return x


# (id, frames from the mean bodies (2, V, 3), weights or None, field, words in the message)
BAD_FRAMES: list[tuple[str, Any, Any, str, str]] = [
    ("all zero", lambda x: np.zeros_like(x), None, "frames", "only zeros"),
    ("constant", lambda x: np.full_like(x, 0.5), None, "frames", "one point"),
    ("on a plane", _flat, None, "frames", "plane"),
    ("on a line", _line, None, "frames", "line"),
    ("millimetres", lambda x: x * 1000.0, None, "frames", "divide by 1000"),
    ("centimetres", lambda x: x * 100.0, None, "frames", "divide by 100"),
    ("kilometres", lambda x: x / 1000.0, None, "frames", "too small for a body"),
    ("far away", lambda x: x + 500.0, None, "frames", "within 100 m"),
    ("NaN", _nan, None, "frames", "frame 1 holds NaN"),
    ("beyond float32", _overflow, None, "frames", "float32"),
    ("int32", lambda x: x.astype(np.int32), None, "frames", "floats"),
    ("bool", lambda x: x > 0, None, "frames", "floats"),
    ("weights negative", lambda x: x, lambda w: -w, "weights", "non-negative"),
    ("weights all zero in a frame", lambda x: x, lambda w: w * [[1.0], [0.0]], "weights", "frame 1"),
    ("weights shape", lambda x: x, lambda w: w[:, :10], "weights", "shape"),
]


@pytest.mark.parametrize(
    ("make", "weigh", "field", "words"), [b[1:] for b in BAD_FRAMES], ids=[b[0] for b in BAD_FRAMES]
)
def test_frames_that_cannot_be_bodies_are_refused_before_any_fit(
    body_service: BodyService, make: Any, weigh: Any, field: str, words: str
) -> None:
    x = _bodies(body_service)
    weights = None if weigh is None else weigh(np.ones(x.shape[:2]))

    def started(p: Progress) -> None:
        raise AssertionError(f"the fit started: {p}")

    with pytest.raises(InvalidInputError) as err:
        body_service.fit_sequence(make(x), weights, Job(on_progress=started))
    assert err.value.field == field and words in err.value.detail, err.value.detail


def test_twenty_thousand_zero_frames_are_refused_at_once(body_service: BodyService) -> None:
    """The abuse case: 20,000 all-zero frames (3.2 GB as float32; a view here) are refused at once, not
    fitted for minutes: by the memory budget (413) from their count, and within it from the first chunk."""
    from bodyfit.service.errors import LimitExceededError

    frames = np.broadcast_to(np.zeros((1, 13348, 3), np.float32), (20_000, 13348, 3))
    with pytest.raises(LimitExceededError, match="memory budget"):
        body_service.check_sequence(frames)
    with pytest.raises(InvalidInputError, match="frame 0 holds only zeros"):
        body_service.check_sequence(frames[:3000])


def test_meshes_are_checked_as_bodies_and_scans_for_their_units(body_service: BodyService) -> None:
    """A mesh in our topology (or SMPL's) is one whole body; a scan in metres read as millimetres spans 2 mm
    and says to send units=m: both before any fit."""
    from bodyfit.io.scans import sample_surface

    body = _bodies(body_service, 1)[0]
    for points, units, field, words in (
        (body, "mm", "units", "units=mm"),
        (sample_surface(body, body_service.model.faces, 2000, seed=1)[0], "mm", "units", "units=m"),
        (np.c_[body[:, :2], np.zeros(len(body))] + [0, 0, 1e-9], "m", "file", "degenerate"),
    ):
        buf = io.BytesIO()
        np.savez(buf, points=points)
        try:
            scan = body_service.read_scan(buf.getvalue(), "npz", units)
            body_service.check_scan(scan)
        except InvalidInputError as exc:
            assert exc.field == field and words in exc.detail, exc.detail
        else:
            raise AssertionError(f"{units} accepted")


def test_domain_errors_inside_a_fit_are_invalid_input(
    body_service: BodyService, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A model-layer input error raised in the middle of a fit (here the scan fitter's ScanError) is the
    client's: InvalidInputError (422 / INVALID_ARGUMENT), never an internal error."""
    from bodyfit.io.scans import ScanError, sample_surface
    from bodyfit.service.errors import as_service_error

    def fit(*args: object, **kwargs: object) -> None:
        raise ScanError("only 4 points are left after thinning to a 1 cm grid")

    monkeypatch.setattr(body_service.fitters.scan, "fit", fit)
    points = sample_surface(_bodies(body_service, 1)[0], body_service.model.faces, 2000, seed=1)[0]
    buf = io.BytesIO()
    np.savez(buf, points=points)
    scan = body_service.read_scan(buf.getvalue(), "npz")
    with pytest.raises(InvalidInputError, match="only 4 points") as err:
        body_service.fit_mesh(scan)
    assert err.value.field == "file"
    # the transports' net for anything else: model input errors -> invalid input, bugs stay internal
    mapped = as_service_error(ScanError("bad scan"))
    assert isinstance(mapped, InvalidInputError) and mapped.detail == "bad scan"
    assert as_service_error(RuntimeError("bug")) is None


def test_non_finite_fits_are_refused_not_encoded(
    body_service: BodyService, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A fit that comes out NaN is an error saying what to check, not a result full of NaN."""
    from types import SimpleNamespace

    body = _bodies(body_service, 1)
    real = body_service.fitters.registered.fit(body)

    def nan_fit(*args: object, **kwargs: object) -> Any:
        return SimpleNamespace(
            shape=real.shape,
            coordinates=real.coordinates * np.nan,
            root=real.root,
            vertices=real.vertices,
            joints=real.joints,
            reports=real.reports,
        )

    monkeypatch.setattr(body_service.fitters.registered, "fit", nan_fit)
    buf = io.BytesIO()
    np.savez(buf, points=body[0])
    with pytest.raises(InvalidInputError, match="46 NaN or infinite values in coordinates") as err:
        body_service.fit_mesh(body_service.read_scan(buf.getvalue(), "npz"))
    assert err.value.field == "file" and "units" in err.value.detail


def test_json_encoders_write_nan_as_null(body_service: BodyService) -> None:
    import json

    from bodyfit.service.formats import Bodies, json_bytes

    doc = json.loads(json_bytes({"a": float("nan"), "b": [np.float32(np.inf), 1.0], "c": np.array([np.nan])}))
    assert doc == {"a": None, "b": [None, 1.0], "c": [None]}
    v = np.full((1, 2, 3), np.nan, np.float32)
    bodies = Bodies(v, np.zeros((0, 3), np.int32), v[:, :1], ("pelvis",))
    parsed = json.loads(encode_bodies(bodies, "json"), parse_constant=lambda c: pytest.fail(c))
    assert parsed["vertices"][0][0] == [None, None, None]


def test_the_memory_budget_refuses_long_sequences_from_their_headers(body_service: BodyService) -> None:
    """BODYFIT_MAX_REQUEST_MB: frames times their measured working memory; a sequence or upgrade over it is
    refused (413) before anything is decompressed, with how many frames fit."""
    from dataclasses import replace as with_limits

    from bodyfit.service.errors import LimitExceededError
    from bodyfit.service.limits import Limits
    from bodyfit.service.uploads import SEQUENCE_BYTES_PER_FRAME, UPGRADE_BYTES_PER_FRAME

    small = with_limits(body_service, limits=Limits(max_request_bytes=100 * 2**20))
    seq_frames, up_frames = (100 * 2**20 // b for b in (SEQUENCE_BYTES_PER_FRAME, UPGRADE_BYTES_PER_FRAME))
    assert small.frame_limit(SEQUENCE_BYTES_PER_FRAME)[0] == seq_frames == 80
    header_only = io.BytesIO()
    with zipfile.ZipFile(header_only, "w") as z:  # declares 81 frames, holds none of them
        z.writestr("frames.npy", _npy_header((seq_frames + 1, body_service.model.n_vertices, 3)))
    with pytest.raises(LimitExceededError, match=f"REQUEST_MB = 100\\) holds {seq_frames} frames"):
        small.read_sequence(header_only.getvalue())
    with pytest.raises(LimitExceededError, match="holds 80 frames"):
        small.check_sequence(np.zeros((seq_frames + 1, body_service.model.n_vertices, 3), np.float32))
    poses = io.BytesIO()
    np.savez(poses, poses=np.zeros((up_frames + 1, 72)), trans=np.zeros((up_frames + 1, 3)))
    with pytest.raises(LimitExceededError, match=f"holds {up_frames} frames"):
        small.read_upgrade(poses.getvalue(), "motion.npz")


def _npy_header(shape: tuple[int, ...]) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "<f4", "fortran_order": False, "shape": shape})
    return buf.getvalue()

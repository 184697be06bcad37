"""Sequences: retargeting real motion (CMU subject 131) onto our skeleton, and fitting registered-mesh
sequences of one person: accuracy on held-out anny bodies, one shape, no seams between chunks, continuous
(unwrapped) pelvis angles through a full turn, no lag, jitter against the input's, and bad input."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import astuple, replace
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest
import torch

from bodyfit.io.bvh import CMU_UNITS, BvhMotion, read_bvh
from bodyfit.io.mocap import MocapFormatError
from bodyfit.models.body.model import BodyModel
from bodyfit.models.errors import NonFiniteError, ShapeError
from bodyfit.models.fitting.common.report import DistanceStats
from bodyfit.models.fitting.registered.fitter import RegisteredFitter, Stage
from bodyfit.models.fitting.retarget.fitter import Retargeted, retarget, wrap_pelvis
from bodyfit.models.fitting.sequence.basins import BasinCheck, settle
from bodyfit.models.fitting.sequence.config import FRAME_STAGES
from bodyfit.models.fitting.sequence.fitter import (
    JitterSum,
    SequenceConfig,
    SequenceFit,
    SequenceFitter,
    SequenceFrames,
    SequenceStats,
    fit_sequence,
    jitter,
)
from bodyfit.models.fitting.sequence.frames import PelvisUnwrap
from bodyfit.models.fitting.sequence.poses import FramePoses
from bodyfit.models.threads import torch_threads

CLIP = Path(__file__).resolve().parents[1] / "data" / "cmu_bvh" / "cmu_131_01_clip.bvh"
LEGS_AND_TRUNK = ("pelvis_", "hip_", "knee_", "lumbar_", "thorax_")
CHUNK = 64


@pytest.fixture(scope="module", autouse=True)
def _one_thread() -> Iterator[None]:
    """One torch thread here: these tests make many small batched calls, which a second thread slows down
    several times over when the other core is busy (the suite runs two workers)."""
    with torch_threads(1):
        yield


@pytest.fixture(scope="module")
def model() -> BodyModel:
    return BodyModel.load()


@pytest.fixture(scope="module")
def motion() -> BvhMotion:
    return read_bvh(CLIP, CMU_UNITS)


@pytest.fixture(scope="module")
def moved(model: BodyModel, motion: BvhMotion) -> Retargeted:
    return retarget(motion, model.skeleton)


@pytest.fixture(scope="module")
def seq_fitter(model: BodyModel) -> SequenceFitter:
    return SequenceFitter(RegisteredFitter(model), SequenceConfig(chunk=CHUNK))


@pytest.fixture(scope="module")
def held_out(model: BodyModel, motion: BvhMotion) -> dict[str, np.ndarray]:
    """The clip turned through three quarters of a turn (the pelvis passes 180 degrees), retargeted onto a
    held-out anny body and skinned by anny's own rig: not in our model's span."""
    pytest.importorskip("anny")
    from benchmarks.fit_sequences import held_out_motion, turning

    data = held_out_motion(model, turning(motion, 0.75), seed=777)
    return {"vertices": data.vertices, "q": data.q, "root": data.root}


@pytest.fixture(scope="module")
def held_out_fit(seq_fitter: SequenceFitter, held_out: dict[str, np.ndarray]) -> SequenceFit:
    return seq_fitter.fit(held_out["vertices"])


# -- retargeting ---------------------------------------------------------------------------------------
def test_retarget_is_in_range_continuous_and_close(model: BodyModel, moved: Retargeted) -> None:
    skel = model.skeleton
    q = moved.coordinates
    assert q.shape == (240, skel.n_dof) and moved.root.shape == (240, 3) and abs(moved.rate - 120) < 0.01
    lo, hi = skel.ranges.T
    q_in = moved.in_range(skel)
    assert ((q_in >= lo) & (q_in <= hi)).all()
    step = np.degrees(np.abs(np.diff(q, axis=0)))
    legs = [k for k, n in enumerate(skel.dof_names) if n.startswith(LEGS_AND_TRUNK)]
    assert step[:, legs].max() < 12.0, step[:, legs].max()  # degrees per frame at 120 fps
    assert np.percentile(step, 99) < 10.0
    assert moved.residual_deg.mean() < 8.0  # RMS bone-direction mismatch, degrees
    # Walking: the knees bend and straighten, the root moves forward at walking speed.
    knee = q[:, skel.dof_index("knee_angle_r")]
    assert np.degrees(np.ptp(knee)) > 40
    speed = np.linalg.norm(moved.root[-1, [0, 2]] - moved.root[0, [0, 2]]) / 2.0
    assert 0.4 < speed < 2.0


def test_retarget_unwraps_a_full_turn(model: BodyModel, motion: BvhMotion) -> None:
    from benchmarks.fit_sequences import turning

    clip = BvhMotion(motion.joints, motion.values[:120], motion.frame_time, motion.units, motion.rotation)
    moved = retarget(turning(clip, 1.25), model.skeleton, iterations=20)
    rot = moved.coordinates[:, model.skeleton.dof_index("pelvis_rotation")]
    assert np.ptp(rot) > np.radians(400)  # beyond [-pi, pi]: unwrapped
    assert np.degrees(np.abs(np.diff(rot))).max() < 8.0
    wrapped = moved.in_range(model.skeleton)[:, model.skeleton.dof_index("pelvis_rotation")]
    assert np.abs(wrapped).max() <= np.pi
    np.testing.assert_allclose(np.cos(wrapped - rot), 1.0, atol=1e-12)


def test_retarget_needs_the_mapped_joints(model: BodyModel, motion: BvhMotion) -> None:
    empty = BvhMotion(motion.joints, motion.values[:0], motion.frame_time)
    with pytest.raises(MocapFormatError, match="no frames"):
        retarget(empty, model.skeleton)
    renamed = tuple(replace(j, name="Pelvis") if j.name == "Hips" else j for j in motion.joints)
    with pytest.raises(MocapFormatError, match="lacks joints the retarget map needs: Hips"):
        retarget(BvhMotion(renamed, motion.values[:2], motion.frame_time), model.skeleton)
    with pytest.raises(ShapeError, match="scales must have shape"):
        retarget(motion, model.skeleton, scales=np.ones((3, 3)))


# -- sequence fitting ------------------------------------------------------------------------------------
def test_held_out_sequence_fits_within_three_millimetres(
    held_out_fit: SequenceFit, held_out: dict[str, np.ndarray]
) -> None:
    fit, x = held_out_fit, held_out["vertices"]
    T = len(x)
    assert fit.registration().shape == x.shape and len(fit.reports) == T
    errors = np.array([r.distances.mean for r in fit.reports])
    assert fit.stats.mean_mm <= 3.0 and errors.max() < 10.0, (fit.stats.mean_mm, errors.max())
    np.testing.assert_allclose(errors.mean(), fit.stats.mean_mm, rtol=1e-6)
    assert all(r.limit_violations == 0 for r in fit.reports)
    # Frame-to-frame jitter no larger than the input's (within 10%), and no lag: each fitted frame is
    # closest to its own input frame, not to a neighbour.
    assert fit.stats.jitter_ratio is not None and fit.stats.jitter_ratio < 1.1, fit.stats
    d0 = np.linalg.norm(fit.registration(1, -1) - x[1:-1], axis=-1).mean()
    for shift in (-1, 1):
        assert d0 < np.linalg.norm(fit.registration(1, -1) - x[1 + shift : T - 1 + shift], axis=-1).mean()


def test_one_shape_for_the_whole_sequence(model: BodyModel, held_out_fit: SequenceFit) -> None:
    fit = held_out_fit
    assert fit.shape.shape == (model.n_shape,)
    T = len(fit.coordinates)
    out = model.forward(
        np.repeat(fit.shape[None], T, axis=0), fit.coordinates_in_range(), fit.root, dtype=torch.float64
    )
    # The registration is the model at the returned parameters, with that one shape in every frame.
    assert np.abs(out.vertices.numpy() - fit.vertices).max() < 2e-4
    assert np.abs(out.joints.numpy() - fit.joints).max() < 2e-4


def test_pelvis_is_unwrapped_through_a_turn(
    model: BodyModel, held_out_fit: SequenceFit, held_out: dict[str, np.ndarray]
) -> None:
    k = model.skeleton.dof_index("pelvis_rotation")
    rot, truth = held_out_fit.coordinates[:, k], held_out["q"][:, k]
    assert np.ptp(truth) > np.radians(200) and np.abs(truth).max() > np.pi  # the subject turns past 180
    assert np.degrees(np.abs(np.diff(rot))).max() < 8.0  # no 2 pi jumps
    assert np.degrees(np.abs(rot - truth)).max() < 6.0
    wrapped = held_out_fit.coordinates_in_range()[:, k]
    np.testing.assert_allclose(wrapped, wrap_pelvis(held_out_fit.coordinates, model.skeleton)[:, k])


def test_no_seams_between_chunks(
    seq_fitter: SequenceFitter, held_out_fit: SequenceFit, held_out: dict[str, np.ndarray]
) -> None:
    fit, x = held_out_fit, held_out["vertices"]
    T = len(x)
    errors = np.array([r.distances.mean for r in fit.reports])
    seams = np.arange(CHUNK, T, CHUNK)
    at_seams = np.r_[seams - 1, seams]
    assert errors[at_seams].max() < 2.0 * np.median(errors) + 1.0, errors[at_seams]
    v = fit.registration()
    acc = np.linalg.norm(v[2:] - 2 * v[1:-1] + v[:-2], axis=-1).mean(1)
    acc_in = np.linalg.norm(x[2:] - 2 * x[1:-1] + x[:-2], axis=-1).mean(1)
    # Second difference centred on each seam frame (index t - 1 in acc): no larger than the input's there
    # beyond what frames away from the seams show.
    excess = acc - acc_in
    assert excess[at_seams - 1].max() <= np.percentile(excess, 95) + 0.5, excess[at_seams - 1]
    # Chunks only split the work: one chunk for the whole clip gives the same fit. Nor do the threads a
    # chunk's frames are split over. Both up to rounding: the batches differ, so float32 rounds differently
    # and a few frames' optimisation carries that further (measured on the benchmark's clip: 0.04 mm mean,
    # 2.3 mm at worst). Frames mixed up between chunks or runs would be centimetres off.
    chunked = seq_fitter.fit(x[:100])
    whole = SequenceFitter(seq_fitter.fitter, SequenceConfig(chunk=T)).fit(x[:100])
    assert seq_fitter.config.workers == 2
    one_thread = SequenceFitter(seq_fitter.fitter, replace(seq_fitter.config, workers=1)).fit(x[:100])
    for other in (whole, one_thread):
        apart = np.linalg.norm(other.registration() - chunked.registration(), axis=-1)
        assert apart.mean() < 2e-4 and apart.max() < 5e-3, (apart.mean(), apart.max())


def test_model_sequence_and_progress(model: BodyModel, moved: Retargeted, seq_fitter: SequenceFitter) -> None:
    """A sequence of our own model (in its span, no anny needed) is recovered closely, with one shape."""
    rng = np.random.default_rng(5)
    T = 72
    shape = rng.normal(size=(1, model.n_shape)) * 0.7
    q = moved.in_range(model.skeleton)[:T]
    x = model.forward(np.repeat(shape, T, axis=0), q, moved.root[:T], dtype=torch.float64).vertices.numpy()
    calls: list[tuple[int, int]] = []
    fit = seq_fitter.fit(x, progress=lambda done, total: calls.append((done, total)))
    assert calls == [(64, T), (T, T)]
    assert fit.stats.mean_mm < 1.5, fit.stats
    assert fit.stats.jitter_ratio is not None and fit.stats.jitter_ratio < 1.1
    assert fit.stats.fps > 0 and fit.stats.frames == T and len(fit.stats.shape_keyframes) == 8
    assert np.degrees(np.abs(fit.coordinates - moved.coordinates[:T])[:, :3]).max() < 3.0


def test_frame_source_streams_in_chunks_and_matches_the_array_fit(
    model: BodyModel, moved: Retargeted, seq_fitter: SequenceFitter
) -> None:
    """A sequence given chunk by chunk through a frame source is fitted as the same sequence in memory,
    the source is never asked for more than one chunk, and the vertices are dropped unless asked for."""
    T = 150
    q = moved.in_range(model.skeleton)[:T]
    shape = np.full((T, model.n_shape), 0.3)
    x = model.forward(shape, q, moved.root[:T], dtype=torch.float64).vertices.numpy()
    w = np.ones(x.shape[:2])
    w[:, :50] = 0.0  # missing vertices carry through the source too
    asked: list[np.ndarray] = []

    def source(idx: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        asked.append(idx)
        return x[idx], w[idx]

    streamed = seq_fitter.fit_frames(source, T)
    in_memory = seq_fitter.fit(x, w)
    assert streamed.vertices is None and in_memory.vertices is not None
    with pytest.raises(ValueError, match="keep_vertices"):
        streamed.registration()
    np.testing.assert_allclose(streamed.coordinates, in_memory.coordinates, atol=1e-9)
    np.testing.assert_allclose(streamed.joints, in_memory.joints, atol=1e-9)
    assert [r.distances for r in streamed.reports] == [r.distances for r in in_memory.reports]
    assert streamed.stats.jitter_fit_mm == pytest.approx(jitter(in_memory.registration(), w))
    assert streamed.stats.mean_mm == pytest.approx(in_memory.stats.mean_mm)
    assert max(len(i) for i in asked) <= CHUNK
    assert np.array_equal(np.concatenate(asked[-3:]), np.arange(T))  # the last pass: every frame once

    def short(idx: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        return x[idx][:-1], None

    with pytest.raises(ShapeError, match="gave 7 frames for 8"):
        seq_fitter.fit_frames(short, T)
    with pytest.raises(ShapeError, match="at least one frame"):
        seq_fitter.fit_frames(source, 0)


def test_final_frames_stream_in_order_while_the_fit_runs(
    model: BodyModel, moved: Retargeted, seq_fitter: SequenceFitter
) -> None:
    """``on_frames`` gets every frame once, in time order, in blocks of the chunk, each as soon as it is
    final (after the next chunk's poses, which its blend reads) and so before the source is asked for the
    chunk after that; the blocks concatenated are the returned fit's arrays, to the bit."""
    T = 2 * CHUNK + 20
    q = moved.in_range(model.skeleton)[:T]
    x = model.forward(
        np.full((T, model.n_shape), 0.2), q, moved.root[:T], dtype=torch.float64
    ).vertices.numpy()
    w = np.ones(x.shape[:2])
    w[:, :50] = 0.0
    events: list[tuple[str, int, int]] = []
    blocks: list[SequenceFrames] = []

    def source(idx: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        events.append(("asked", int(idx[0]), int(idx[-1]) + 1))
        return x[idx], w[idx]

    def on_frames(block: SequenceFrames) -> None:
        events.append(("block", block.start, block.stop))
        blocks.append(block)

    fit = seq_fitter.fit_frames(source, T, keep_vertices=True, on_frames=on_frames)
    c1, c2 = CHUNK, 2 * CHUNK
    last_pass = [("asked", 0, c1), ("asked", c1, c2), ("block", 0, c1), ("asked", c2, T)]
    assert events[-6:] == [*last_pass, ("block", c1, c2), ("block", c2, T)]
    assert [(b.start, b.stop) for b in blocks] == [(0, c1), (c1, c2), (c2, T)]
    for name, whole in [
        ("coordinates", fit.coordinates),
        ("root", fit.root),
        ("vertices", fit.registration()),
        ("joints", fit.joints),
        ("error_mm", np.array([r.distances.mean for r in fit.reports])),
    ]:
        streamed = np.concatenate([getattr(b, name) for b in blocks])
        assert streamed.dtype == whole.dtype and np.array_equal(streamed, whole), name
    assert blocks[0].vertices.shape == (c1, model.n_vertices, 3) and blocks[0].joints.shape[0] == c1
    # fit_sequence and fit pass the hook on; a sequence shorter than a chunk is one block
    few: list[SequenceFrames] = []
    short = fit_sequence(seq_fitter.fitter, x[:5], config=seq_fitter.config, on_frames=few.append)
    assert [(b.start, b.stop) for b in few] == [(0, 5)]
    assert np.array_equal(few[0].coordinates, short.coordinates)


def test_pelvis_unwrapped_block_by_block_is_numpys_unwrap_of_the_whole() -> None:
    """Fed in blocks of any size (one frame, uneven), the unwrapped pelvis angles are np.unwrap's of the
    whole sequence to the bit: turns of many laps, steps of exactly pi either way, and still frames."""
    rng = np.random.default_rng(3)
    T, n_dof, dofs = 400, 6, [0, 2, 5]
    angles = np.cumsum(rng.normal(0.0, 1.2, (T, n_dof)), axis=0)
    angles[100:104, 0] = angles[99, 0] + np.pi * np.array([1, 0, -1, 0]).cumsum()
    angles[200:210, 2] = angles[199, 2]
    q = np.pi - np.mod(np.pi - angles, 2 * np.pi)  # wrapped into (-pi, pi]
    expected = q.copy()
    for k in dofs:
        expected[:, k] = np.unwrap(q[:, k])
    for sizes in ([T], [1, 1, 398], [7, 64, 1, 128, 200]):
        unwrap = PelvisUnwrap(dofs)
        bounds = np.cumsum([0, *sizes])
        got = np.concatenate([unwrap(q[lo:hi]) for lo, hi in pairwise(bounds)])
        assert np.array_equal(got, expected), sizes
    assert np.abs(np.diff(expected[:, dofs], axis=0)).max() <= np.pi


def test_blend_is_centred_and_leaves_the_pelvis(
    model: BodyModel, moved: Retargeted, seq_fitter: SequenceFitter
) -> None:
    """The blend acts after the per-frame fits: the blended joint coordinates are exactly the centred
    three-frame blend of the unblended ones, across chunks too; the pelvis and the end frames are kept."""
    T = CHUNK + 36
    x = model.forward(
        np.zeros((T, model.n_shape)), moved.in_range(model.skeleton)[:T], moved.root[:T], dtype=torch.float64
    ).vertices.numpy()
    b = 0.2
    raw = SequenceFitter(seq_fitter.fitter, replace(seq_fitter.config, blend=0.0)).fit(x).coordinates
    blended = SequenceFitter(seq_fitter.fitter, replace(seq_fitter.config, blend=b)).fit(x).coordinates
    pelvis = np.array([n.startswith("pelvis_") for n in model.dof_names])
    expected = (1 - 2 * b) * raw[1:-1] + b * (raw[:-2] + raw[2:])
    np.testing.assert_allclose(blended[1:-1, ~pelvis], expected[:, ~pelvis], atol=1e-9)
    np.testing.assert_allclose(blended[:, pelvis], raw[:, pelvis], atol=1e-9)
    np.testing.assert_allclose(blended[[0, -1]], raw[[0, -1]], atol=1e-9)
    with pytest.raises(ValueError, match="blend"):
        SequenceFitter(model, SequenceConfig(blend=0.5))


def test_jitter_definition() -> None:
    t = np.arange(5.0)
    x = np.zeros((5, 2, 3))
    x[:, 0, 0] = t**2 / 1000.0  # constant acceleration: second difference 2 mm
    assert jitter(x) == pytest.approx(1.0)  # mean over the two points: (2 + 0) / 2
    assert np.isnan(jitter(x[:2]))
    rng = np.random.default_rng(0)
    y, w = rng.normal(size=(11, 4, 3)), rng.integers(0, 2, size=(11, 4)).astype(float)
    running = JitterSum()
    for part in np.array_split(np.arange(11), [1, 2, 6]):  # chunks of 1, 1, 4 and 5 frames
        running.add(y[part], w[part])
    assert running.mm() == pytest.approx(jitter(y, w))


def test_undefined_jitter_is_none_with_the_reason_never_nan() -> None:
    """Two frames have no second difference and a still input no ratio: None (JSON null) and a note saying
    why, never NaN (which no JSON parser reads)."""
    short = SequenceStats.measured(2, 1.0, 0.5, float("nan"), float("nan"), (0, 1))
    assert (short.jitter_input_mm, short.jitter_fit_mm, short.jitter_ratio) == (None, None, None)
    assert short.jitter_note is not None and "three consecutive frames" in short.jitter_note
    still = SequenceStats.measured(3, 1.0, 0.5, 0.0, 0.02, (0, 1, 2))
    assert still.jitter_input_mm == 0.0 and still.jitter_fit_mm == 0.02 and still.jitter_ratio is None
    assert still.jitter_note is not None and "does not move" in still.jitter_note
    moving = SequenceStats.measured(10, 2.0, 0.5, 2.0, 1.0, (0,))
    assert moving.jitter_ratio == 0.5 and moving.jitter_note is None and moving.fps == 5.0
    for stats in (short, still, moving):
        assert not any(isinstance(v, float) and np.isnan(v) for v in stats.to_dict().values())


def test_per_frame_statistics_at_once_are_each_frame_s() -> None:
    """DistanceStats.of_rows: every row kept (float32, no copy), the same columns dropped in every row, and
    rows that keep different entries or hold NaN (one row at a time) all agree with DistanceStats.of."""
    rng = np.random.default_rng(3)
    d = rng.uniform(0.0, 0.01, size=(6, 50)).astype(np.float32)
    every = np.ones(d.shape, bool)
    same = every.copy()
    same[:, ::3] = False
    mixed = rng.uniform(size=d.shape) < 0.7
    with_nan = d.copy()
    with_nan[2, 4] = np.nan
    for metres, keep in ((d, every), (d, same), (d, mixed), (with_nan, every)):
        got = DistanceStats.of_rows(metres, keep)
        for row, stats in enumerate(got):
            want = DistanceStats.of(metres[row][keep[row]])
            for a, b in zip(astuple(stats), astuple(want), strict=True):
                assert a == pytest.approx(b, rel=1e-5)
    assert DistanceStats.of_rows(d, every)[0].max == pytest.approx(float(d[0].max()) * 1000.0, rel=1e-6)


def test_bad_sequences_raise(model: BodyModel, seq_fitter: SequenceFitter) -> None:
    V = model.n_vertices
    with pytest.raises(ShapeError, match="T >= 1"):
        seq_fitter.fit(np.zeros((0, V, 3)))
    with pytest.raises(ShapeError, match=f"\\(T, {V}, 3\\)"):
        seq_fitter.fit(np.zeros((V, 3)))
    with pytest.raises(ShapeError, match="our template's vertices"):
        seq_fitter.fit(np.zeros((3, V - 1, 3)))
    bad = np.zeros((3, V, 3))
    bad[1, 5, 2] = np.nan
    with pytest.raises(NonFiniteError):
        seq_fitter.fit(bad)
    with pytest.raises(ShapeError, match="vertex weights"):
        seq_fitter.fit(np.zeros((3, V, 3)), weights=np.ones((2, V)))
    with pytest.raises(ValueError, match="keep the shape frozen"):
        SequenceFitter(
            model,
            SequenceConfig(
                frame_stages=(
                    Stage(name="x", coordinates="all", shape="all", vertices="subset", iterations=5),
                )
            ),
        )
    with pytest.raises(ValueError, match="at least 1"):
        SequenceFitter(model, SequenceConfig(stride=0))


# -- one basin along time ------------------------------------------------------------------------------
def _frame_problems(
    model: BodyModel, seq_fitter: SequenceFitter, q: np.ndarray, root: np.ndarray
) -> FramePoses:
    """The pose problems of our mean body's skins at q (T, n_dof), root (T, 3), in the world frame."""
    T = len(q)
    x = model.forward(np.zeros((T, model.n_shape)), q, root, dtype=torch.float64).vertices.numpy()
    frames = (x.astype(np.float32), np.ones(x.shape[:2]), np.repeat(np.eye(3)[None], T, 0), np.zeros((T, 3)))
    return FramePoses(seq_fitter.pose_fitter, frames, np.zeros((1, model.n_shape)), FRAME_STAGES, 1)


def test_frames_stuck_at_a_limit_are_re_solved_from_their_neighbours(
    model: BodyModel, moved: Retargeted, seq_fitter: SequenceFitter
) -> None:
    """Frames whose fit starts at the elbow's upper limit stay there (the bounded mapping is flat at a
    limit: 150 degrees against the input's 47), while the input moves by a degree a frame; re-solved from
    their neighbours they follow the input again. The frames fitted well are not touched."""
    skel = model.skeleton
    T, stuck, elbow = 12, [5, 6, 7], skel.dof_index("elbow_flex_r")
    q_true, root = moved.in_range(skel)[:T], moved.root[:T]
    problems = _frame_problems(model, seq_fitter, q_true, root)
    q0 = q_true.copy()
    q0[stuck, elbow] = skel.ranges[elbow, 1]
    q, r = problems.refit(np.arange(T), q0, root)
    assert np.degrees(q[stuck, elbow]).min() > 145.0  # the fit alone stays at the limit
    settled, r_settled, kept = settle(q, r, problems, BasinCheck(), np.arange(skel.n_dof))
    assert kept == len(stuck)
    assert np.degrees(np.abs(settled[:, elbow] - q_true[:, elbow])).max() < 3.0
    assert problems.losses(np.arange(T), settled, r_settled).max() < 5.0  # mm^2
    others = np.setdiff1d(np.arange(T), stuck)
    np.testing.assert_array_equal(settled[others], q[others])


def test_a_jump_the_input_makes_is_kept(
    model: BodyModel, moved: Retargeted, seq_fitter: SequenceFitter
) -> None:
    """The input's own jump (the elbow bends 40 degrees between two frames) moves the skin with the input: it
    is not questioned, and nothing is re-solved."""
    skel = model.skeleton
    T, elbow = 8, skel.dof_index("elbow_flex_r")
    q_true, root = moved.in_range(skel)[:T].copy(), moved.root[:T]
    q_true[4:, elbow] += np.radians(40.0)
    problems = _frame_problems(model, seq_fitter, q_true, root)
    q, r = problems.refit(np.arange(T), q_true, root)
    settled, _, kept = settle(q, r, problems, BasinCheck(), np.arange(skel.n_dof))
    assert kept == 0
    np.testing.assert_array_equal(settled, q)
    assert np.degrees(settled[4, elbow] - settled[3, elbow]) > 35.0
    with pytest.raises(ValueError, match="jump"):
        BasinCheck(jump=0.0)
    with pytest.raises(ValueError, match="rounds"):
        BasinCheck(rounds=-1)

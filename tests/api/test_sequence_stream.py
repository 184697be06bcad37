"""Sequence fits stream their chunks while the fit runs: the re-slicing of the fitter's blocks into chunk
events, the job's partial-result sink, and the order of events on the REST stream."""

from __future__ import annotations

import io
import json
from collections.abc import Iterator
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from bodyfit import wire as w
from bodyfit.api.rest.app import create_app
from bodyfit.api.results import SequenceChunker
from bodyfit.api.settings import ServiceSettings
from bodyfit.models.fitting.sequence.fitter import SequenceFrames
from bodyfit.service.core import BodyService, SynthRequest
from bodyfit.service.errors import JobCancelledError
from bodyfit.service.jobs import Job


def _blocks(sizes: list[int], seed: int = 0) -> list[SequenceFrames]:
    """Consecutive blocks of random frames (3 DOFs, 4 vertices, 2 joints) of the given sizes."""
    rng = np.random.default_rng(seed)
    out, start = [], 0
    for k in sizes:
        out.append(
            SequenceFrames(
                start=start,
                stop=start + k,
                coordinates=rng.normal(size=(k, 3)),
                root=rng.normal(size=(k, 3)),
                vertices=rng.normal(size=(k, 4, 3)).astype(np.float32),
                joints=rng.normal(size=(k, 2, 3)),
                error_mm=rng.uniform(size=k),
            )
        )
        start += k
    return out


@pytest.mark.parametrize(("sizes", "chunk"), [([3, 3, 3, 1], 4), ([5], 2), ([1, 1, 1], 5), ([4, 4], 4)])
def test_chunker_reslices_blocks_into_chunks(sizes: list[int], chunk: int) -> None:
    blocks = _blocks(sizes)
    events: list[w.SequenceChunkEvent] = []
    chunker = SequenceChunker(chunk, events.append)
    emitted_before_flush = []
    for b in blocks:
        chunker(b)
        emitted_before_flush.append(len(events))
    chunker.flush()
    total = sum(sizes)
    assert [(e.start, e.stop) for e in events] == [
        (lo, min(total, lo + chunk)) for lo in range(0, total, chunk)
    ]
    # a chunk goes out as soon as its frames are in, not at the end
    assert emitted_before_flush[-1] == total // chunk
    for name in ("coordinates", "root", "vertices", "error_mm"):
        whole = np.concatenate([getattr(b, name) for b in blocks])
        sent = np.concatenate([getattr(e.arrays, name).to_numpy() for e in events])
        np.testing.assert_array_equal(sent, whole)
    joints = np.concatenate([e.arrays.joints.to_numpy() for e in events])
    np.testing.assert_array_equal(joints, np.concatenate([b.joints for b in blocks]).astype(np.float32))


def test_chunker_refuses_blocks_out_of_order() -> None:
    first, second = _blocks([2, 2])
    chunker = SequenceChunker(3, lambda e: None)
    with pytest.raises(ValueError, match="out of order"):
        chunker(second)
    chunker(first)
    with pytest.raises(ValueError, match="out of order"):
        chunker(first)


def test_job_emit_needs_a_sink_and_stops_when_cancelled() -> None:
    with pytest.raises(RuntimeError, match="on_event"):
        Job().emit("chunk")
    got: list[Any] = []
    job = Job(on_event=got.append)
    job.emit("chunk")
    job.cancel()
    with pytest.raises(JobCancelledError):
        job.emit("late")
    assert got == ["chunk"]


@pytest.fixture()
def small_blocks(body_service: BodyService) -> Iterator[BodyService]:
    """The service with its sequence fitter streaming blocks of 2 frames (instead of its default)."""
    fitter = body_service.fitters.sequence
    config = fitter.config
    fitter.config = replace(config, chunk=2)
    try:
        yield body_service
    finally:
        fitter.config = config


def _frames(service: BodyService, n: int) -> np.ndarray:
    return service.synthesize(SynthRequest(coordinates={"knee_angle_l": np.linspace(0, 1, n)})).vertices


def test_service_hands_out_frames_before_the_fit_ends(small_blocks: BodyService) -> None:
    log: list[tuple[str, int]] = []
    job = Job(on_progress=lambda p: log.append(("progress", p.done)))
    fit = small_blocks.fit_sequence(
        _frames(small_blocks, 6), job=job, on_frames=lambda b: log.append(("frames", b.start))
    )
    assert [i for kind, i in log if kind == "frames"] == [0, 2, 4]
    first_block = log.index(("frames", 0))
    assert any(kind == "progress" for kind, _ in log[first_block + 1 :]), log
    assert len(fit.coordinates) == 6


def _npz(**arrays: Any) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def test_rest_stream_sends_chunks_between_progress_events(small_blocks: BodyService) -> None:
    app = create_app(ServiceSettings(), service=small_blocks)
    files = {"file": ("seq.npz", _npz(frames=_frames(small_blocks, 6)))}
    with (
        TestClient(app, raise_server_exceptions=False) as client,
        client.stream(
            "POST", "/v1/fit/sequence?chunk=2", files=files, headers={"accept": "application/x-ndjson"}
        ) as r,
    ):
        kinds = [json.loads(line)["event"] for line in r.iter_lines() if line]
        doc = client.post("/v1/fit/sequence?chunk=4", files=files).json()
    assert kinds.count("chunk") == 3 and kinds[-1] == "result"
    assert "progress" in kinds[kinds.index("chunk") + 1 :], kinds  # the first chunk came mid-fit
    # the one-document answer still holds every chunk, in order, before the summary's fields
    assert [(c["start"], c["stop"]) for c in doc["chunks"]] == [(0, 4), (4, 6)]
    assert doc["limit_violations"] == 0

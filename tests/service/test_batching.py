"""Micro-batching: concurrent requests share model calls and each gets exactly its own rows."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import pytest

from bodyfit.service.batching import SynthBatcher
from bodyfit.service.core import BodyService


class CountingSession:
    """Wraps a session, recording the batch size of every call."""

    def __init__(self, session: Any) -> None:
        self.session = session
        self.batches: list[int] = []

    def run(self, outputs: Any, feeds: dict[str, np.ndarray]) -> Any:
        self.batches.append(len(feeds["shape"]))
        return self.session.run(outputs, feeds)


def test_concurrent_requests_get_their_own_rows(body_service: BodyService) -> None:
    rng = np.random.default_rng(1)
    model = body_service.model
    lo, hi = model.skeleton.ranges.T
    inputs = [
        (
            rng.normal(size=(b, model.n_shape)).astype(np.float32),
            rng.uniform(lo * 0.5, hi * 0.5, (b, model.skeleton.n_dof)).astype(np.float32),
            rng.normal(size=(b, 3)).astype(np.float32),
        )
        for b in (1, 2, 1, 3, 1, 1, 2, 1)
    ]
    counting = CountingSession(body_service.session)
    batcher = SynthBatcher(counting, max_bodies=64)
    with ThreadPoolExecutor(8) as pool:
        results = list(pool.map(lambda x: batcher.submit(*x).result(timeout=30), inputs * 4))
    batcher.close()
    for (c, q, r), (vertices, joints) in zip(inputs * 4, results, strict=True):
        ref_v, ref_j = body_service.session.run(None, {"shape": c, "coordinates": q, "root": r})
        assert vertices.shape == ref_v.shape and np.abs(vertices - ref_v).max() < 1e-5
        assert np.abs(joints - ref_j).max() < 1e-5
    assert sum(counting.batches) == sum(len(c) for c, _, _ in inputs * 4)
    assert len(counting.batches) < len(inputs) * 4  # some calls were shared


def test_a_failing_call_fails_every_caller_of_its_batch() -> None:
    class Broken:
        def run(self, outputs: Any, feeds: dict[str, np.ndarray]) -> Any:
            raise RuntimeError("model call failed")

    batcher = SynthBatcher(Broken(), max_bodies=8)
    futures = [batcher.submit(np.zeros((1, 2)), np.zeros((1, 3)), np.zeros((1, 3))) for _ in range(3)]
    for f in futures:
        with pytest.raises(RuntimeError, match="model call failed"):
            f.result(timeout=10)
    batcher.close()

"""Shared fixtures. Every test runs from a fresh clone: only files in the repository are used."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from bodyfit.models.skeleton import Skeleton


@pytest.fixture(scope="session")
def skeleton() -> Skeleton:
    return Skeleton.load()


def random_pose(skel: Skeleton, n: int, seed: int, rajagopal_only: bool = False) -> np.ndarray:
    """(n, n_dof) coordinates uniform within range; extension DOFs zero when ``rajagopal_only``."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(skel.ranges[:, 0], skel.ranges[:, 1], (n, skel.n_dof))
    if rajagopal_only:
        mask = np.array([c.rajagopal for c in skel.spec.coordinates])
        q[:, ~mask] = 0.0
    return q


@pytest.fixture(autouse=True)
def _deterministic() -> None:
    torch.manual_seed(0)

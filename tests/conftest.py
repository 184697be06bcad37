"""Shared fixtures. Every test runs from a fresh clone: only files in the repository are used."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest
import torch

from bodyfit.models.skeleton import Skeleton

if TYPE_CHECKING:
    from bodyfit.service.core import BodyService


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


@pytest.fixture(scope="session")
def body_service() -> BodyService:
    """The service core over the built-in assets, with the SMPL-format test model file for upgrades (one per
    test process; it takes seconds to load)."""
    from bodyfit.service.core import BodyService
    from bodyfit.service.limits import Limits

    smpl = Path(__file__).resolve().parent / "data" / "smpl_format" / "smpl_like_model.npz"
    return BodyService.load(limits=Limits(max_batch=64, queue_seconds=5.0), threads=1, smpl_model=smpl)


@pytest.fixture(autouse=True)
def _deterministic() -> None:
    torch.manual_seed(0)

"""Fitting configs are typed and keyword-only, and a bad value fails where the config is built, with a message
naming the field, the value and the allowed ones, instead of a KeyError deep inside a fit."""

from __future__ import annotations

import dataclasses
import re
from typing import Any

import pytest
import torch

from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.registered.fitter import (
    DEFAULT_STAGES,
    RegisteredFitConfig,
    RegisteredFitter,
    Stage,
)
from bodyfit.models.fitting.registered.stages import COORDINATE_SETS, SHAPE_SETS, VERTEX_SETS
from bodyfit.models.fitting.scan.config import (
    DEFAULT_BRANCHES,
    DEFAULT_PHASES,
    UPPER_BODY_PHASES,
    ScanBranch,
    ScanFitConfig,
    ScanPhase,
)
from bodyfit.models.fitting.sequence.fitter import FRAME_STAGES, KEY_STAGES, SequenceConfig
from bodyfit.models.fitting.sequence.offsets import OffsetConfig

GOOD: dict[str, Any] = {
    "name": "x",
    "coordinates": "all",
    "shape": "none",
    "vertices": "subset",
    "iterations": 5,
}


@pytest.mark.parametrize(
    ("field", "typo", "allowed"),
    [
        ("coordinates", "al", COORDINATE_SETS),
        ("shape", "bones", SHAPE_SETS),
        ("vertices", "subet", VERTEX_SETS),
        ("metric", "Coarse", VERTEX_SETS),
    ],
)
def test_a_stage_typo_names_the_field_the_value_and_the_choices(
    field: str, typo: str, allowed: tuple[str, ...]
) -> None:
    choices = ", ".join(repr(a) for a in allowed)
    message = f"Stage.{field} must be one of {choices}; got {typo!r}"
    with pytest.raises(ValueError, match=re.escape(message)):
        Stage(**{**GOOD, field: typo})
    # replace() is how stages are tweaked: it checks too
    with pytest.raises(ValueError, match=re.escape(message)):
        changes: dict[str, Any] = {field: typo}
        dataclasses.replace(DEFAULT_STAGES[0], **changes)


def test_stages_and_phases_are_keyword_only() -> None:
    with pytest.raises(TypeError):
        Stage("trunk", "trunk", "bone", "trunk", 10)  # type: ignore[call-arg]
    stage = Stage(**GOOD)
    with pytest.raises(TypeError):
        ScanPhase(stage, 150.0, 3, 500)  # type: ignore[call-arg]
    with pytest.raises(TypeError):
        RegisteredFitConfig(DEFAULT_STAGES)  # type: ignore[call-arg]
    with pytest.raises(TypeError):
        SequenceConfig(8)  # type: ignore[call-arg]
    with pytest.raises(TypeError):
        ScanBranch(frozenset({"fine"}), 1e-3)  # type: ignore[call-arg]


@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda: Stage(**{**GOOD, "iterations": 0}), "Stage.iterations must be at least 1; got 0"),
        (lambda: Stage(**{**GOOD, "iterations": "10"}), "Stage.iterations must be at least 1; got '10'"),
        (
            lambda: ScanPhase(stage=Stage(**GOOD), sigma_mm=0.0, keep=1, scan_points=500),
            "ScanPhase.sigma_mm must be positive; got 0.0",
        ),
        (
            lambda: ScanPhase(stage=Stage(**GOOD), sigma_mm=10.0, keep=0, scan_points=500),
            "ScanPhase.keep must be at least 1; got 0",
        ),
        (
            lambda: ScanPhase(stage="pose", sigma_mm=10.0, keep=1, scan_points=500),  # type: ignore[arg-type]
            "ScanPhase.stage must be a Stage; got 'pose'",
        ),
        (
            lambda: ScanPhase(stage=Stage(**GOOD), sigma_mm=10.0, keep=1, scan_points=500, rounds=0),
            "ScanPhase.rounds must be at least 1; got 0",
        ),
        (
            lambda: ScanBranch(metric_phases=frozenset({"fine"}), damping=-1.0),
            "ScanBranch.damping must be at least 0.0; got -1.0",
        ),
        (lambda: ScanFitConfig(workers=0), "ScanFitConfig.workers must be at least 1; got 0"),
        (lambda: ScanFitConfig(branches=()), "ScanFitConfig.len(branches) must be at least 1; got 0"),
        (
            lambda: RegisteredFitConfig(dtype=torch.float16),
            "RegisteredFitConfig.dtype must be one of torch.float32, torch.float64; got torch.float16",
        ),
        (
            lambda: RegisteredFitConfig(subset_size=0),
            "RegisteredFitConfig.subset_size must be at least 1; got 0",
        ),
        (lambda: RegisteredFitConfig(stages=()), "RegisteredFitConfig.len(stages) must be at least 1; got 0"),
        (lambda: SequenceConfig(chunk=0), "SequenceConfig.chunk must be at least 1; got 0"),
        (lambda: OffsetConfig(smoothness=-1.0), "OffsetConfig.smoothness must be at least 0.0; got -1.0"),
        (lambda: OffsetConfig(max_residual=0.0), "OffsetConfig.max_residual must be positive; got 0.0"),
        (lambda: SequenceConfig(workers=0), "SequenceConfig.workers must be at least 1; got 0"),
        (lambda: SequenceConfig(blend=0.5), "SequenceConfig.blend must be in [0, 0.5); got 0.5"),
        (
            lambda: SequenceConfig(frame_stages=(Stage(**{**GOOD, "shape": "all"}),)),
            "stage 'x' fits it (SequenceConfig.key_stages and frame_stages need shape='none')",
        ),
    ],
)
def test_a_bad_setting_fails_where_the_config_is_built(build: object, message: str) -> None:
    with pytest.raises(ValueError, match=re.escape(message)):
        build()  # type: ignore[operator]


def test_the_default_tables_are_valid_and_use_every_name_the_fitter_selects() -> None:
    """The typed choices are exactly the vertex sets, coordinate masks and shape masks a fitter builds, so a
    stage that passes its checks never misses a table; the defaults are built through the same checks."""
    fitter = RegisteredFitter(BodyModel.load())
    assert set(VERTEX_SETS) == set(fitter.index) == set(fitter.decoders)
    assert set(COORDINATE_SETS) == set(fitter.dof_mask)
    assert set(SHAPE_SETS) == set(fitter.shape_mask)
    stages = [
        *DEFAULT_STAGES,
        *KEY_STAGES,
        *FRAME_STAGES,
        *(p.stage for p in (*DEFAULT_PHASES, *UPPER_BODY_PHASES)),
    ]
    for stage in stages:
        assert dataclasses.replace(stage) == stage  # rebuilt through __post_init__
    assert ScanFitConfig().branches == DEFAULT_BRANCHES

"""The scan fit's helper process (``ScanFitConfig.processes=2``): it takes the second branch and half of the
early phases' hypotheses, the fit is the one a single process gives, and a helper that dies leaves the fits
to the calling process, which still gives that fit, until a new helper is started."""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from bodyfit.io.scans import sample_surface
from bodyfit.models.body.anny_posed import random_poses
from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.scan.config import DEFAULT_PHASES, ScanFitConfig
from bodyfit.models.fitting.scan.fitter import ScanFitter

BRANCHED = ("shape", "limbs", "fine")
HELPER_START_SECONDS = 180.0  # it starts in about 5 s; the suite's other worker may hold the other core
SHORT = ScanFitConfig(
    phases=tuple(
        dataclasses.replace(p, stage=dataclasses.replace(p.stage, iterations=4)) for p in DEFAULT_PHASES
    ),
    nonrigid=None,
)


@pytest.fixture(scope="module")
def model() -> BodyModel:
    return BodyModel.load()


@pytest.fixture()
def one_thread() -> Iterator[None]:
    """Torch's ops on one thread, as in the helper (its intra-op threads may round differently)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_a_helper_process_gives_the_one_process_fit(model: BodyModel, one_thread: None) -> None:
    rng = np.random.default_rng(21)
    q = random_poses(model.skeleton, 1, rng, spread=0.3)
    body = model.forward(np.zeros((1, model.n_shape)), q, np.zeros((1, 3)), dtype=torch.float64)
    points, _ = sample_surface(body.vertices[0].numpy(), model.faces, 20_000, seed=21)
    points = points @ np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]).T  # searched
    alone = ScanFitter(model, SHORT).fit(points)
    assert alone.report.extra["branch_scores"]  # two branches, the orientation searched: work to share
    fitter = ScanFitter(model, dataclasses.replace(SHORT, processes=2))
    helper = fitter.helper
    assert helper is not None
    try:
        assert fitter.wait_for_helper(HELPER_START_SECONDS)
        lines: list[str] = []
        shared = fitter.fit(points, lambda done, total, line: lines.append(line) if done else None)
        # half of the orientation phase's and the pose phase's hypotheses, and the second branch
        assert helper.completed == 3
        for fit in (shared, alone):
            assert len(fit.report.extra["branch_scores"]) == 2
        assert shared.report.extra["branch_scores"] == alone.report.extra["branch_scores"]
        np.testing.assert_array_equal(shared.coordinates, alone.coordinates)
        np.testing.assert_array_equal(shared.registration, alone.registration)
        names = [line.split(": robust")[0] for line in lines]
        assert len(names) == fitter.progress_steps() and names[:2] == ["orient", "pose"]
        assert names[-1] == "valley"
        # the helper's lines, passed on in order
        assert [n for n in names if n.startswith("branch 2")] == [f"branch 2: {n}" for n in BRANCHED]

        os.kill(helper.pid, signal.SIGKILL)
        helper.restart_after = 3600.0
        helper_less = fitter.fit(points)
        assert not helper.ready and helper.completed == 3 and helper.restarts == 0
        np.testing.assert_array_equal(helper_less.registration, alone.registration)

        # once restart_after has passed, the next fit starts a new helper (and fits without it meanwhile)
        helper.restart_after = 0.0
        fitter.fit(points)
        assert helper.restarts == 1 and fitter.wait_for_helper(HELPER_START_SECONDS)
        again = fitter.fit(points)
        assert helper.completed == 6
        np.testing.assert_array_equal(again.registration, alone.registration)
    finally:
        fitter.close()
    assert not helper.alive


def _run_script(tmp_path: Path, *lines: str) -> subprocess.CompletedProcess[str]:
    """Run a script that makes a two-process fitter at its top level, then ``lines``; it must succeed."""
    script = tmp_path / "script.py"
    script.write_text(
        "from bodyfit.models.body.model import BodyModel\n"
        "from bodyfit.models.fitting.scan.config import ScanFitConfig\n"
        "from bodyfit.models.fitting.scan.fitter import ScanFitter\n"
        "fitter = ScanFitter(BodyModel.load(), ScanFitConfig(processes=2))\n"
        + "".join(f"{x}\n" for x in lines)
    )
    done = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=HELPER_START_SECONDS
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return done


def test_a_script_without_a_main_guard_gets_its_helper(tmp_path: Path) -> None:
    """The helper is a fresh interpreter, not a multiprocessing child that imports the caller's script: a
    script that makes a fitter at its top level, with no ``if __name__ == "__main__"`` guard, gets a
    helper once (spawned children would run the script again and never start)."""
    done = _run_script(
        tmp_path, "print('ready', fitter.wait_for_helper(120.0), flush=True)", "fitter.close()"
    )
    assert done.stdout.count("ready True") == 1, done.stdout


def test_a_helper_stopped_while_it_starts_exits_quietly(tmp_path: Path) -> None:
    """A fitter closed at once (a command that ends before its helper has started) stops the helper without
    waiting for its imports and without a traceback from it."""
    done = _run_script(
        tmp_path,
        "fitter.close()",
        "assert fitter.helper is not None",
        "print('alive', fitter.helper.alive, flush=True)",
    )
    assert "alive False" in done.stdout
    assert "Traceback" not in done.stderr, done.stderr[-2000:]


def test_processes_are_one_or_two() -> None:
    with pytest.raises(ValueError, match="processes must be 1 or 2"):
        ScanFitConfig(processes=3)

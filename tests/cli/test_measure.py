"""``bodyfit measure``: measurements of the bodies in a parameters file; bodies built from measurements."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from bodyfit.cli import app
from bodyfit.models.anthropometry.definitions import MEASUREMENTS

runner = CliRunner()


def test_measure_a_parameters_file(tmp_path: Path) -> None:
    path = tmp_path / "fit.npz"
    np.savez(path, shape=np.zeros((2, 32)), coordinates=np.zeros((2, 46)))
    result = runner.invoke(app, ["measure", str(path), "--json"])
    assert result.exit_code == 0, result.output
    values = json.loads(result.stdout)["measurements"]
    assert list(values) == list(MEASUREMENTS)
    assert len(values["stature"]) == 2 and 1.5 < values["stature"][0] < 1.9
    table = runner.invoke(app, ["measure", str(path)])
    assert table.exit_code == 0 and "stature mm" in " ".join(table.stdout.split())


def test_build_a_body_from_measurements(tmp_path: Path) -> None:
    out = tmp_path / "body.npz"
    args = ["measure", "-s", "stature=1.80", "-s", "mass=80", "--sex", "male", "--out", str(out), "--json"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    assert abs(doc["residuals"]["stature"]) < 0.005 and abs(doc["residuals"]["weightkg"]) < 1.0
    assert np.load(out)["shape"].shape == (1, 32)


def test_bad_requests_exit_with_a_message(tmp_path: Path) -> None:
    result = runner.invoke(app, ["measure", "-s", "statur=1.8"])
    assert result.exit_code == 2 and "did you mean 'stature'" in result.output
    result = runner.invoke(app, ["measure", "-s", "waist=3"])
    assert result.exit_code == 2 and "waistcircumference = 3 m" in result.output
    result = runner.invoke(app, ["measure"])
    assert result.exit_code == 2 and "--set" in result.output
    path = tmp_path / "bad.npz"
    np.savez(path, coordinates=np.zeros((1, 46)))
    result = runner.invoke(app, ["measure", str(path)])
    assert result.exit_code == 2 and "shape" in result.output

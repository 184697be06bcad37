"""The benchmarks' shared command line: ``--json`` prints one parseable object whatever the run prints."""

from __future__ import annotations

import json
import os
from typing import Any

import pytest

from benchmarks.bench_cli import bench_main


def _noisy_run(quick: bool) -> dict[str, Any]:
    print("a library's banner")  # as warp prints on import
    os.write(1, b"MODEL: a native library's report\n")  # as OpenSim's C++ prints
    return {"quick": quick, "value_ms": 1.5}


def test_json_output_is_the_result_alone(capfd: pytest.CaptureFixture[str]) -> None:
    bench_main(_noisy_run, "test", "quick", ["--quick", "--json"])
    out, err = capfd.readouterr()
    assert json.loads(out) == {"quick": True, "value_ms": 1.5}
    assert "banner" in err and "native library" in err  # moved, not lost


def test_plain_output_lists_the_keys(capfd: pytest.CaptureFixture[str]) -> None:
    bench_main(_noisy_run, "test", "quick", [])
    out, _ = capfd.readouterr()
    assert "value_ms: 1.5" in out and "quick: False" in out

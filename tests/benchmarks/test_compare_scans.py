"""The scan-by-scan comparison of two raw-scan runs (``benchmarks/compare_scans.py``)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.compare_scans import load_rows, main, moved, summary


def _write(path: Path, errors: list[float]) -> Path:
    conditions = ("clean", "holes")
    lines = [
        json.dumps({"k": k, "condition": conditions[k % 2], "registration_mm": mm, "seconds": 3.0 + k,
                    "cpu_seconds": 4.0})
        for k, mm in enumerate(errors)
    ]  # fmt: skip
    path.write_text("\n".join(lines) + "\n")
    return path


def test_summary_and_moved_scans(tmp_path: Path) -> None:
    before = load_rows(_write(tmp_path / "a.jsonl", [2.0, 60.0, 3.0, 8.0]))
    after = load_rows(_write(tmp_path / "b.jsonl", [2.5, 12.0, 3.1, 11.5]))
    s = summary(before)
    assert s["scans"] == 4
    assert s["mean_mm"] == pytest.approx(18.25)
    assert s["median_mm"] == pytest.approx(5.5)
    assert s["within_10mm"] == pytest.approx(0.75)
    assert s["by_condition_mm"] == {"clean": 2.5, "holes": 34.0}
    assert s["seconds"] == pytest.approx(4.5)
    assert moved(before, after, 3.0) == [(1, "holes", 60.0, 12.0), (3, "holes", 8.0, 11.5)]
    assert moved(before, after, 50.0) == []


def test_cli_counts_better_and_worse(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    a = _write(tmp_path / "a.jsonl", [2.0, 60.0, 3.0, 8.0])
    b = _write(tmp_path / "b.jsonl", [2.5, 12.0, 3.1, 11.5])
    main([str(a), str(b), "--margin", "3"])
    out = capsys.readouterr().out
    assert "1 better, 1 worse" in out
    assert "scan   1     holes:  60.00 ->  12.00 mm" in out


def test_a_file_that_is_not_rows_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    good = _write(tmp_path / "a.jsonl", [2.0])
    bad = tmp_path / "b.jsonl"
    bad.write_text('{"k": 0, "condition": "clean"}\n')
    with pytest.raises(SystemExit):
        main([str(good), str(bad)])
    assert "b.jsonl:1 is not a scan row" in capsys.readouterr().err

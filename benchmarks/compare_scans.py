"""Compare two raw-scan runs scan by scan (the ``--rows`` files of ``benchmarks/fit_scans.py``).

The 102-scan mean is carried by a few gross errors that the platform's floating-point rounding can tip
either way, so a change is judged on runs in one environment, scan by scan: each run's mean, median and
share within 10 mm, its mean by condition and its mean seconds (wall and CPU), then the scans whose
registration error moved by more than ``--margin`` mm.

Usage::

    python benchmarks/fit_scans.py --json --rows before.jsonl   # on the old code
    python benchmarks/fit_scans.py --json --rows after.jsonl    # on the new code
    python benchmarks/compare_scans.py before.jsonl after.jsonl [--margin 3]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np


def load_rows(path: str | Path) -> dict[int, dict[str, Any]]:
    """The rows of a ``--rows`` file by scan index ``k``; a ValueError names a line that is not a row."""
    rows = {}
    for n, line in enumerate(Path(path).read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
            rows[int(row["k"])] = row
            float(row["registration_mm"])
        except (ValueError, KeyError, TypeError) as exc:
            raise ValueError(
                f"{path}:{n} is not a scan row (a JSON object with 'k' and 'registration_mm', as "
                f"fit_scans.py --rows writes): {exc}"
            ) from None
    return rows


def summary(rows: dict[int, dict[str, Any]]) -> dict[str, Any]:
    """Mean, median and share within 10 mm of the registration error, its mean by condition, and the mean
    wall and CPU seconds of the rows (scan index -> row)."""
    mm = np.array([r["registration_mm"] for r in rows.values()])
    conditions = sorted({r["condition"] for r in rows.values()})
    return {
        "scans": len(rows),
        "mean_mm": round(float(mm.mean()), 2),
        "median_mm": round(float(np.median(mm)), 2),
        "within_10mm": round(float(np.mean(mm <= 10.0)), 3),
        "by_condition_mm": {
            c: round(float(np.mean([r["registration_mm"] for r in rows.values() if r["condition"] == c])), 2)
            for c in conditions
        },
        "seconds": round(float(np.mean([r["seconds"] for r in rows.values()])), 2),
        "cpu_seconds": round(float(np.mean([r.get("cpu_seconds", np.nan) for r in rows.values()])), 2),
    }


def moved(
    before: dict[int, dict[str, Any]], after: dict[int, dict[str, Any]], margin: float
) -> list[tuple[int, str, float, float]]:
    """(k, condition, before mm, after mm) of the scans in both runs whose registration error moved by more
    than ``margin`` mm, by scan index."""
    return [
        (k, before[k]["condition"], before[k]["registration_mm"], after[k]["registration_mm"])
        for k in sorted(set(before) & set(after))
        if abs(after[k]["registration_mm"] - before[k]["registration_mm"]) > margin
    ]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("before", help="rows of the old code (fit_scans.py --rows)")
    parser.add_argument("after", help="rows of the new code")
    parser.add_argument("--margin", type=float, default=3.0, help="mm a scan must move to be listed")
    args = parser.parse_args(argv)
    try:
        before, after = load_rows(args.before), load_rows(args.after)
    except (OSError, ValueError) as exc:
        parser.error(str(exc))
    for name, rows in (("before", before), ("after", after)):
        print(f"{name}: {json.dumps(summary(rows))}")
    changes = moved(before, after, args.margin)
    better = sum(a < b for _, _, b, a in changes)
    print(f"moved by more than {args.margin:g} mm: {better} better, {len(changes) - better} worse")
    for k, condition, b, a in changes:
        print(f"  scan {k:3d} {condition:>9}: {b:6.2f} -> {a:6.2f} mm")


if __name__ == "__main__":
    main()

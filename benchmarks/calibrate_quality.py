"""Calibrate the raw-scan fit's quality estimate (:mod:`bodyfit.models.fitting.common.quality`) and write the
coefficient file the package ships.

1. Collect: fit the pose x corruption matrix of :mod:`scan_matrix` (every pose and corruption, the orientation
   searched and hinted) on held-out bodies drawn with the calibration seeds (:data:`CALIBRATION_SEEDS`; the
   test set of ``fit_confidence.py`` uses other seeds), one JSON row per fit (``--rows``; rows already in
   the file are kept, so a collection can run in parts: ``--part k/n``).
2. Fit: read every row's features again from its report (:func:`quality.scan_features`) and fit the
   quantile regressions of :func:`quality.fit_quality_model` to the true registration errors; write them to
   ``bodyfit/models/fitting/common/quality_model.json`` (``--out``).

Usage::

    python benchmarks/calibrate_quality.py --rows build/quality_rows.jsonl --collect [--part 0/2]
    python benchmarks/calibrate_quality.py --rows build/quality_rows.jsonl   # fit and write the model
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import scan_matrix  # benchmarks/ is on sys.path when this runs as a script
import torch

from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common import quality

CALIBRATION_SEEDS = (5101, 5102)  # the test set (fit_confidence.py) draws with 5301
OUT = Path(quality.__file__).with_name("quality_model.json")


def collect(rows_path: Path, seed: int, part: tuple[int, int], points: int) -> None:
    """Append the rows of the matrix drawn with ``seed`` (cells whose index is ``part[0]`` modulo
    ``part[1]``) to ``rows_path`` as each fit ends."""
    k, n = part
    width = len(scan_matrix.CORRUPTIONS)
    rows = scan_matrix.run_matrix(
        tuple(scan_matrix.POSES), scan_matrix.CORRUPTIONS, seed, points, lambda i, j: (i * width + j) % n == k
    )
    for row in rows:
        with rows_path.open("a") as out:
            out.write(json.dumps(row) + "\n")


def read_rows(path: Path) -> list[dict[str, Any]]:
    """The rows of a JSON-lines file."""
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def calibrate(rows: list[dict[str, Any]], model: BodyModel) -> quality.QualityModel:
    """The quality model fitted to the rows that have a report."""
    fitted = [r for r in rows if "report" in r]
    bind, ranges = model.bind_coordinates, model.skeleton.ranges
    X = np.stack([quality.row_features(r, bind, ranges) for r in fitted])
    y = np.array([r["registration_mm"] for r in fitted])
    return quality.fit_quality_model(X, y)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rows", type=Path, required=True, help="the collected fits (JSON lines)")
    parser.add_argument("--collect", action="store_true", help="fit the matrix and append its rows")
    parser.add_argument("--seed", type=int, default=CALIBRATION_SEEDS[0], choices=CALIBRATION_SEEDS)
    parser.add_argument("--part", default="0/1", help="k/n: collect every n-th cell from the k-th")
    parser.add_argument("--points", type=int, default=scan_matrix.POINTS)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.collect:
        k, n = (int(x) for x in args.part.split("/"))
        collect(args.rows, args.seed, (k, n), args.points)
        return
    fitted = calibrate(read_rows(args.rows), BodyModel.load())
    args.out.write_text(json.dumps(fitted.to_json(), indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

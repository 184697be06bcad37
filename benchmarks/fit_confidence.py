"""How far a raw-scan fit's confidence can be trusted, and how often the fit fails grossly, on held-out bodies
in whole-body poses under every scan corruption, with the orientation searched and hinted.

What is measured
----------------
* The matrix of :mod:`scan_matrix`: 11 poses (A-pose, T-pose, arms raised at full abduction with the
  scapulae, arms flexed forward and up, crossed arms, hands on hips, crouching, sitting, lying, walking,
  random) x 12 corruptions (clean, upside down, randomly rotated, millimetres, front half, back half, 2 cm
  voxels, a floor plane, noise and outliers, one depth view, holes, loose clothing), one held-out body per
  cell drawn with :data:`TEST_SEED` (the quality estimate is calibrated with other seeds:
  ``calibrate_quality.py``), each fitted twice: with the orientation searched (the default) and with the
  true orientation passed in. Quick: 22 of the 132 cells (two corruptions per pose, every corruption in
  about two poses), 20,000 points per scan; full: every cell, 30,000 points.
* ``conf_auroc``: the area under the ROC curve of the report's ``predicted_error_mm`` for telling the fits
  whose true registration error (mean vertex distance to the true body) exceeds 25 mm from the rest;
  ``conf_recall_good``: the share of fits within 10 mm that the report calls confident;
  ``confident_over_25mm``: how many fits over 25 mm it calls confident (target 0).
* ``gross_failure_rate_searched`` / ``_hinted``: the share of fits that fail grossly (mean registration
  error over 15 mm, or an anatomical joint more than 50 mm from the true one, or the scan refused);
  ``gross_failure_rate`` the worse of the two. The joints include the spine's, which the surface
  constrains least: ``gross_failure_rate_limb_joints`` counts the limb and head joints only.
* The table (printed without ``--json``) lists per pose and corruption the gross failures as
  ``searched/hinted``.

Usage::

    python benchmarks/fit_confidence.py [--quick] [--json] [--rows ROWS.jsonl] [--from-rows ROWS.jsonl]

``--rows`` writes every fit's row as it ends; ``--from-rows`` scores rows written earlier instead of fitting
(with the quality model shipped now).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import scan_matrix  # benchmarks/ is on sys.path when this runs as a script

from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common import quality
from bodyfit.models.fitting.scan.report import MAX_UNEXPLAINED, MIN_INLIER_FRACTION

TEST_SEED = 5301  # calibration draws with calibrate_quality.CALIBRATION_SEEDS
GOOD_MM = 10.0
QUICK_POINTS = 20_000
SPINE_JOINTS = ("lumbosacral", "thoracolumbar", "cervicothoracic")


def quick_cell(i: int, j: int) -> bool:
    """The quick run's cells: pose i meets corruptions j with i + j divisible by 6."""
    return (i + j) % 6 == 0


def auroc(score: np.ndarray, positive: np.ndarray) -> float | None:
    """The area under the ROC curve of ``score`` (n,) for ``positive`` (n,) bool (ties counted half: the
    Mann-Whitney U statistic over the pairs); None without both classes."""
    pos, neg = score[positive], score[~positive]
    if not len(pos) or not len(neg):
        return None
    greater = (pos[:, None] > neg[None, :]).sum() + 0.5 * (pos[:, None] == neg[None, :]).sum()
    return float(greater / (len(pos) * len(neg)))


def judged(row: dict[str, Any], model: BodyModel) -> tuple[float, bool]:
    """A fitted row's predicted error (mm) and confidence by the quality model shipped now, from the row's
    report (as the report itself states them: the prediction, and the hard reasons of joint limits, too few
    inliers and a head-and-shoulders fit), so that rows written earlier score alike."""
    report = row["report"]
    features = quality.row_features(row, model.bind_coordinates, model.skeleton.ranges)
    prediction = quality.shipped_model().predict(features)
    extra = report["extra"]
    hard = (
        report["limit_violations"] > 0
        or extra["inlier_fraction"] < MIN_INLIER_FRACTION
        or extra.get("unexplained_fraction", 0.0) > MAX_UNEXPLAINED
        or extra.get("single_view") is not None
        or extra["fitted_part"] != "whole body"
    )
    return prediction.error_mm, prediction.confident and not hard


def gross_limbs(row: dict[str, Any], model: BodyModel) -> bool:
    """Gross by the mean error or a joint other than the spine's (refused rows are gross)."""
    if "report" not in row:
        return True
    keep = [k for k, name in enumerate(model.joint_names) if name not in SPINE_JOINTS]
    worst = max(row["joint_mm"][k] for k in keep)
    return bool(row["registration_mm"] > scan_matrix.GROSS_MEAN_MM or worst > scan_matrix.GROSS_JOINT_MM)


def summarise(rows: list[dict[str, Any]], model: BodyModel) -> dict[str, Any]:
    """The keys of the module docstring from the matrix's rows."""
    fitted = [r for r in rows if "report" in r]
    error = np.array([r["registration_mm"] for r in fitted])
    predicted, confident = (np.array(v) for v in zip(*(judged(r, model) for r in fitted), strict=True))
    good = error <= GOOD_MM

    def rate(mode: str, gross: Any = lambda r: r["gross"]) -> float:
        return round(float(np.mean([gross(r) for r in rows if r["mode"] == mode])), 3)

    searched, hinted = rate("searched"), rate("hinted")
    cells: dict[str, dict[str, str]] = {}
    for pose in scan_matrix.POSES:
        for corruption in scan_matrix.CORRUPTIONS:
            ran = [r for r in rows if r["pose"] == pose and r["corruption"] == corruption]
            if ran:
                counts = [[r["gross"] for r in ran if r["mode"] == m] for m in scan_matrix.MODES]
                text = "/".join(str(sum(c)) if c else "-" for c in counts)  # "-": that mode not run
                cells.setdefault(pose, {})[corruption] = text
    limbs = max(rate(m, lambda r: gross_limbs(r, model)) for m in scan_matrix.MODES)
    return {
        "conf_auroc": None if (a := auroc(predicted, error > quality.BAD_MM)) is None else round(a, 4),
        "conf_recall_good": round(float(confident[good].mean()), 3) if good.any() else None,
        "confident_over_25mm": int((confident & (error > quality.BAD_MM)).sum()),
        "gross_failure_rate": max(searched, hinted),
        "gross_failure_rate_searched": searched,
        "gross_failure_rate_hinted": hinted,
        "gross_failure_rate_limb_joints": limbs,
        "conf_fits": len(rows),
        "conf_refused": len(rows) - len(fitted),
        "conf_confident_share": round(float(confident.mean()), 3),
        "conf_over_25mm": int((error > quality.BAD_MM).sum()),
        "conf_bound_mm": round(quality.shipped_model().confident_below_mm, 2),
        "conf_registration_median_mm": round(float(np.median(error)), 2),
        "gross_cells": cells,
    }


def run(quick: bool, rows_path: str | None = None, from_rows: str | None = None) -> dict[str, Any]:
    """Fit the matrix (quick: :func:`quick_cell`'s cells) or read its rows (``from_rows``) and summarise;
    with ``rows_path``, write each fit's row to it as a JSON line as the fit ends."""
    model = BodyModel.load()
    if from_rows:
        rows = [json.loads(line) for line in Path(from_rows).read_text().splitlines() if line.strip()]
        return summarise(rows, model)
    rows = []
    points = QUICK_POINTS if quick else scan_matrix.POINTS
    cells = quick_cell if quick else (lambda i, j: True)
    poses = tuple(scan_matrix.POSES)
    for row in scan_matrix.run_matrix(poses, scan_matrix.CORRUPTIONS, TEST_SEED, points, cells):
        rows.append(row)
        if rows_path:
            with open(rows_path, "a" if len(rows) > 1 else "w") as out:
                out.write(json.dumps(row) + "\n")
    return summarise(rows, model)


def show(result: dict[str, Any]) -> None:
    """The keys, then the gross failures per pose (rows) and corruption (columns) as searched/hinted."""
    for key, value in result.items():
        if key != "gross_cells":
            print(f"{key:>32}: {value}")
    cells = result["gross_cells"]
    names = [c for c in scan_matrix.CORRUPTIONS if any(c in row for row in cells.values())]
    print("\ngross failures (searched/hinted) per pose and corruption; '.' or '-' not run")
    print(f"{'':>16}" + "".join(f"{c[:10]:>11}" for c in names))
    for pose, row in cells.items():
        print(f"{pose:>16}" + "".join(f"{row.get(c, '.'):>11}" for c in names))


def main(argv: list[str] | None = None) -> None:
    from bench_cli import bench_main  # benchmarks/ is on sys.path when this runs as a script

    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--rows", metavar="ROWS.jsonl", help="also write every fit's row to this file")
    parser.add_argument("--from-rows", metavar="ROWS.jsonl", help="score rows written earlier; no fitting")
    known, rest = parser.parse_known_args(argv)
    bench_main(
        lambda quick: run(quick, known.rows, known.from_rows),
        __doc__.split("\n")[0],
        "22 of the 132 cells, 20,000 points per scan",
        rest,
        show,
    )


if __name__ == "__main__":
    main()

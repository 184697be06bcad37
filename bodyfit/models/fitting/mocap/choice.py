"""Static or motion calibration: both are fitted when a static trial is given, compared on the motion, and
the choice is reported with its reason.

OpenSim's workflow calibrates from the static trial (S. L. Delp et al., "OpenSim: Open-Source Software to
Create and Analyze Dynamic Simulations of Movement", IEEE Transactions on Biomedical Engineering 54(11),
2007): its anatomical markers set the segment scales and the zero of coordinates such as the ankle's (a toe
marker on a shoe), which the motion alone cannot. A static trial can still disagree with the motion
(another standing pose than the lab's setup assumes, markers moved between trials), and then the motion's
own calibration explains the markers better. ``auto`` keeps the static calibration while its mean marker
error on the motion is within :data:`STATIC_TOLERANCE` of the motion calibration's (the price of the
anatomical zeros) and falls back to the motion calibration otherwise; an explicit choice is kept, with
the comparison in the report either way.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

STATIC_TOLERANCE = 1.2  # auto keeps the static calibration while its error is within this factor
SCALE_TOLERANCE = 0.15  # a segment whose scales differ by more between the two calibrations is reported


def choose_calibration(mode: str, errors_mm: Mapping[str, float]) -> tuple[str, str]:
    """The calibration kept (``"static"`` or ``"motion"``) and why.

    Args:
        mode: ``"auto"``, ``"static"`` or ``"motion"`` (as the user asked).
        errors_mm: mean marker error on the motion (mm) of each calibration fitted (``"static"``,
            ``"motion"``); with one entry, that one is kept.
    """
    if len(errors_mm) == 1:
        (only,) = errors_mm
        return only, "the only calibration possible without a static trial"
    static, motion = errors_mm["static"], errors_mm["motion"]
    ratio = static / motion
    compared = (
        f"static {static:.1f} mm, motion {motion:.1f} mm mean marker error on the motion "
        f"(static / motion = {ratio:.2f})"
    )
    if mode != "auto":
        advice = ""
        if mode == "static" and ratio > STATIC_TOLERANCE:
            advice = (
                "; the static trial disagrees with the motion: calibration='auto' or 'motion' fits it better"
            )
        return mode, f"asked for ({compared}){advice}"
    if ratio <= STATIC_TOLERANCE:
        return "static", (
            f"static kept: within {STATIC_TOLERANCE}x of the motion calibration ({compared}); its anatomical "
            "markers set the scales and the coordinates' zeros"
        )
    return "motion", (
        f"motion chosen: the static trial disagrees with the motion, its calibration is more than "
        f"{STATIC_TOLERANCE}x worse ({compared})"
    )


def scale_differences(
    static: np.ndarray, motion: np.ndarray, segments: list[str], measured: np.ndarray
) -> dict[str, float]:
    """Segments whose scales (n_seg, 3) differ between the two calibrations by more than
    :data:`SCALE_TOLERANCE` (largest relative difference over the axes), name -> that difference, among
    the ``measured`` (n_seg,) bool ones (those carrying at least two markers: the others' scales come from
    the prior more than from the data)."""
    rel = np.abs(static - motion) / np.maximum(np.abs(motion), 1e-9)
    worst = rel.max(axis=1)
    return {segments[i]: float(worst[i]) for i in np.flatnonzero((worst > SCALE_TOLERANCE) & measured)}


def choice_report(
    mode: str, chosen: str, reason: str, errors_mm: Mapping[str, float], scales: Mapping[str, np.ndarray],
    segments: list[str], measured: np.ndarray, check: Mapping[str, Any] | None,
) -> tuple[dict[str, Any], list[str]]:  # fmt: skip
    """``report.extra["calibration_choice"]`` and notes for the report.

    Args:
        scales: (n_seg, 3) of each calibration fitted; measured: (n_seg,) bool, segments carrying at least
            two markers; check: :meth:`~.static_check.StaticCheck.as_dict` or
            None without a static trial.
    """
    notes: list[str] = []
    differ: dict[str, float] = {}
    if "static" in scales and "motion" in scales:
        differ = scale_differences(scales["static"], scales["motion"], segments, measured)
        if differ:
            listed = ", ".join(f"{s} {d * 100:.0f}%" for s, d in differ.items())
            notes.append(
                f"the static trial's segment scales differ from the motion's by more than "
                f"{SCALE_TOLERANCE * 100:.0f}%: {listed}"
            )
    worse = len(errors_mm) == 2 and chosen != min(errors_mm, key=lambda k: errors_mm[k])
    if worse or (mode == "auto" and chosen == "motion"):
        notes.append(f"calibration: {reason}")
    out = {
        "requested": mode,
        "chosen": chosen,
        "reason": reason,
        "marker_error_mm": dict(errors_mm),
        "scale_differences": differ,
        "static_check": dict(check) if check is not None else None,
    }
    return out, notes

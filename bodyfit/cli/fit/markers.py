"""``bodyfit fit markers``: motion-capture marker trials (.trc, .c3d) to coordinates, a scaled OpenSim
subject and an error report per trial (:func:`bodyfit.models.fitting.mocap.fitter.fit_markers`)."""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

if TYPE_CHECKING:
    from bodyfit.io.mocap import MarkerTrial
    from bodyfit.models.body.model import BodyModel
    from bodyfit.models.fitting.mocap.fitter import CalibrationMode, MarkerFit
    from bodyfit.models.fitting.mocap.marker_sets import MarkerSetName

MARKER_SUFFIXES = (".trc", ".c3d")


@dataclass(frozen=True)
class MarkerOptions:
    """What the command line says about the trials: static: a standing trial of the same subject;
    static_pose: ``NAME=DEGREES`` items (coordinates held in the static trial's pose); calibration and
    marker_set: as :func:`fit_markers` takes them; up, forward: the lab's axes (``y``, ``-z``, ...); skin:
    also estimate the subject's skin (:mod:`bodyfit.models.fitting.mocap.skin`) and write it."""

    static: Path | None = None
    static_pose: Sequence[str] = ()
    calibration: str = "auto"
    marker_set: str = "auto"
    up: str = "y"
    forward: str = "x"
    skin: bool = True


def is_marker_file(path: Path) -> bool:
    return path.suffix.lower() in MARKER_SUFFIXES


def parse_static_pose(items: Sequence[str]) -> dict[str, float]:
    """``["ankle_angle_r=0.5", ...]`` (degrees) -> ``{"ankle_angle_r": 0.00873, ...}`` (radians).

    Raises:
        ValueError: an item that is not NAME=DEGREES with a finite number, or a name given twice.
    """
    out: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        name = name.strip()
        try:
            degrees = float(value)
        except ValueError:
            degrees = math.nan
        if not sep or not name or not math.isfinite(degrees):
            raise ValueError(f"--static-pose takes NAME=DEGREES (e.g. ankle_angle_r=0.5); got {item!r}")
        if name in out:
            raise ValueError(f"--static-pose gives {name} twice")
        out[name] = math.radians(degrees)
    return out


def fit_marker_trials(
    trials: Sequence[Path], out: Path, options: MarkerOptions, echo: Callable[[str], None]
) -> list[dict[str, Any]]:
    """Fit each trial, write ``<stem>.mot`` and ``<stem>.osim`` (the scaled subject with its calibrated
    markers) to ``out`` and ``fit.json`` (one record per trial); with ``options.skin`` also the subject's
    skin through the motion, ``<stem>_skin.npz`` (vertices (T, V, 3) float32 m, faces (F, 3), times (T,))
    and ``<stem>_skin.glb`` (the middle frame); returns the records. ``echo`` gets one line per trial and
    step.

    Raises:
        BodyfitError (unreadable files, marker sets, coordinates), ValueError (bad options), OSError.
    """
    from bodyfit.io.mocap import lab_rotation, read_markers
    from bodyfit.models.body.model import BodyModel
    from bodyfit.models.fitting.mocap.fitter import fit_markers

    held = parse_static_pose(options.static_pose)
    rotation = lab_rotation(options.up, options.forward)
    static = None if options.static is None else read_markers(options.static, rotation)
    motions = [read_markers(path, rotation) for path in trials]  # every file read before any fit
    model = BodyModel.load()
    records = []
    out.mkdir(parents=True, exist_ok=True)
    for path, motion in zip(trials, motions, strict=True):
        fit = fit_markers(
            motion,
            static,
            # the command line's strings are checked by fit_markers, which names the valid choices
            cast("MarkerSetName", options.marker_set),
            model=model,
            static_pose=held or None,
            calibration=cast("CalibrationMode", options.calibration),
        )
        files = fit.write(out, model.skeleton.spec, path.stem)
        if options.skin:
            echo(f"{path.name}: estimating the skin from the markers ({len(fit.times)} frames)")
            files.update(write_skin(model, motion, fit, out, path.stem))
        report = fit.report
        records.append(
            {
                "trial": str(path),
                "frames": len(fit.times),
                "marker_set": fit.marker_set,
                "files": {kind: str(p) for kind, p in files.items()},
                **report.to_dict(),
            }
        )
        flag = "ok" if report.confident else "LOW CONFIDENCE: " + "; ".join(report.reasons)
        echo(
            f"{path.name} ({fit.marker_set}, {len(fit.times)} frames, calibrated from "
            f"{report.extra['calibration']}): markers {report.distances.mean:.1f} mm mean, "
            f"{report.distances.p95:.1f} mm p95, {flag}"
        )
        for line in _calibration_lines(report.extra):
            echo(f"  {line}")
    (out / "fit.json").write_text(json.dumps(records, indent=1) + "\n")
    return records


def write_skin(
    model: BodyModel, motion: MarkerTrial, fit: MarkerFit, out: Path, stem: str
) -> dict[str, Path]:
    """The subject's skin from the markers (:func:`~bodyfit.models.fitting.mocap.skin.fit_skin`) posed
    through the motion: ``<stem>_skin.npz`` and ``<stem>_skin.glb`` (the middle frame) in ``out``."""
    import numpy as np

    from bodyfit.models.fitting.mocap.fitter import observed_positions
    from bodyfit.models.fitting.mocap.skin import fit_skin
    from bodyfit.service.formats import Bodies, encode_bodies

    observed = observed_positions(motion, list(fit.markers.names))
    skin = fit_skin(model, fit.scales, fit.coordinates, fit.root, observed)
    vertices = skin.vertices(model, fit.coordinates, fit.root)
    faces = model.faces.astype(np.int32)
    npz = out / f"{stem}_skin.npz"
    np.savez(npz, vertices=vertices, faces=faces, times=fit.times, shape=skin.shape)
    middle = vertices[len(vertices) // 2][None]
    glb = out / f"{stem}_skin.glb"
    glb.write_bytes(encode_bodies(Bodies(middle, faces, np.zeros((1, 0, 3), np.float32), ()), "glb"))
    return {"skin": npz, "skin_glb": glb}


def _calibration_lines(extra: dict[str, Any]) -> list[str]:
    """The calibration choice (with a static trial), the unobservable coordinates and those at a joint limit
    in most frames, one line each."""
    lines = []
    choice = extra.get("calibration_choice") or {}
    if len(choice.get("marker_error_mm", {})) > 1:
        lines.append(f"calibration: {choice['reason']}")
    hidden = extra.get("unobservable") or {}
    if hidden:
        lines.append(f"held near neutral, the markers cannot determine them: {', '.join(hidden)}")
    pinned = extra.get("at_limit") or {}
    if pinned:
        lines.append(f"at a joint limit in most frames (check the markers): {', '.join(pinned)}")
    return lines

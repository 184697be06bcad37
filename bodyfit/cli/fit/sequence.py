"""``bodyfit fit sequence``: registered mesh sequences (.npz holding ``frames`` (T, V, 3) in metres, our
topology) to one shape and a pose per frame (:meth:`bodyfit.service.core.BodyService.fit_sequence`)."""

from __future__ import annotations

import json
import zipfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from bodyfit.models.fitting.registered.fitter import FixedBody
    from bodyfit.service.core import BodyService

SEQUENCE_KEY = "frames"


def is_sequence_file(path: Path) -> bool:
    """An .npz whose arrays include ``frames`` (a scan's hold ``points`` or ``vertices``); False for
    anything else, unreadable files included (the scan reader then says what is wrong)."""
    if path.suffix.lower() != ".npz":
        return False
    try:
        with zipfile.ZipFile(path) as archive:
            names = {Path(name).stem for name in archive.namelist()}
    except (OSError, zipfile.BadZipFile):
        return False
    return SEQUENCE_KEY in names and not names & {"points", "vertices"}


def fit_sequence_files(
    service: BodyService,
    paths: Sequence[Path],
    out: Path,
    fps: float,
    echo: Callable[[str], None],
    body: FixedBody | None = None,
) -> list[dict[str, Any]]:
    """Fit each sequence, write ``<stem>.npz`` (shape, coordinates, root, vertices, joints, per-frame
    error_mm) and ``<stem>.mot`` (``fps`` frames per second) to ``out`` and ``fit.json`` (one record per
    sequence); returns the records. ``echo`` gets progress and a summary line per sequence. ``body``: a
    subject's (:meth:`BodyService.subject_body`): no shape fit, every frame is that body.

    Raises:
        ServiceError (unreadable or malformed files, too many frames), BodyfitError, OSError.
    """
    import numpy as np

    from bodyfit.models.skeleton.opensim_export import write_mot
    from bodyfit.service.jobs import Job, Progress

    def show(p: Progress) -> None:
        if p.done and p.message:
            echo(f"  {p.message}")

    loaded = [service.read_sequence(path.read_bytes()) for path in paths]  # every file checked first
    out.mkdir(parents=True, exist_ok=True)
    model = service.model
    records = []
    for path, (frames, weights) in zip(paths, loaded, strict=True):
        echo(f"{path.name}: {len(frames)} frames")
        fit = service.fit_sequence(frames, weights, Job(on_progress=show), body=body)
        errors = np.array([r.distances.mean for r in fit.reports])
        np.savez_compressed(
            out / f"{path.stem}.npz",
            allow_pickle=False,
            shape=fit.shape,
            coordinates=fit.coordinates,
            root=fit.root,
            vertices=fit.registration(),
            joints=fit.joints.astype(np.float32),
            error_mm=errors,
            dof_names=np.array(model.dof_names),
            joint_names=np.array(model.joint_names),
        )
        spec = model.skeleton.spec
        write_mot(out / f"{path.stem}.mot", spec, fit.coordinates, fit.root, fps=fps, name=path.stem)
        stats = fit.stats
        records.append(
            {
                "sequence": str(path),
                "frames": len(frames),
                "stats": stats.to_dict(),
                "error_mm": {"mean": float(errors.mean()), "max": float(errors.max())},
                "limit_violations": sum(r.limit_violations for r in fit.reports),
                "confident_frames": sum(r.confident for r in fit.reports),
            }
        )
        ratio = stats.jitter_ratio
        smooth = f"jitter {ratio:.2f}x the input's" if ratio is not None else f"jitter: {stats.jitter_note}"
        echo(
            f"{path.name} (sequence, {len(frames)} frames): mean {errors.mean():.2f} mm, worst frame "
            f"{errors.max():.2f} mm, {stats.fps:.0f} frames/s, {smooth}, "
            f"{records[-1]['confident_frames']} of {len(frames)} frames confident"
        )
    (out / "fit.json").write_text(json.dumps(records, indent=1) + "\n")
    return records

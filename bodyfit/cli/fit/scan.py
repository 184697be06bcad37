"""``bodyfit fit scan``: meshes and scans, each routed by its topology (our 13,348 vertices, SMPL's 6,890, or
a raw scan) through :meth:`bodyfit.service.core.BodyService.fit_mesh` in this process."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from bodyfit.models.fitting.registered.fitter import FixedBody
    from bodyfit.service.core import BodyService
    from bodyfit.service.hints import ScanHints

# raw scans in one `bodyfit fit` from which a second process pays for its own start-up (loading torch and
# the model): below this, fitting in this process alone is as fast
HELPER_SCANS = 3


def fit_mesh_files(
    service: BodyService,
    paths: Sequence[Path],
    out: Path,
    units: str,
    processes: int | None,
    echo: Callable[[str], None],
    note: Callable[[str], None],
    hints: ScanHints | None = None,
    body: FixedBody | None = None,
) -> list[dict[str, Any]]:
    """Fit each mesh or scan (read first, all of them, in ``units``: auto, m or mm, as the server reads them:
    NaN or infinite points, the missing pixels of depth cameras and organized PCD clouds, are dropped and
    ``echo`` says how many) and write ``fit.npz``
    (shape, coordinates, root, vertices, joints per input), ``fit.json`` (one report per input),
    ``registration_<k>.ply`` and ``fit.mot`` to ``out``; returns the records. ``processes``: 1 or 2 (a
    helper process for raw scans), None: 2 from :data:`HELPER_SCANS` raw scans on. ``echo`` gets a summary
    line per input, ``note`` the progress. ``hints`` (up, facing, pose class, sex, height) go with every
    input (:meth:`BodyService.fit_mesh`); fit.npz's ``to_model`` (B, 4, 4) maps each input's frame, in which
    the vertices and joints lie, to the frame its parameters pose the model in. ``body``: a subject's
    (:meth:`BodyService.subject_body`), held fixed in every fit.

    Raises:
        BodyfitError (unreadable files, bad scans), ServiceError, OSError.
    """
    import numpy as np
    import trimesh

    from bodyfit.io.scans import load_scan
    from bodyfit.models.skeleton.opensim_export import write_mot
    from bodyfit.service.core import RAW_SCAN
    from bodyfit.service.jobs import Job, Progress

    def show(p: Progress) -> None:
        if p.message not in ("", "done"):
            note(f"  {p.message}")

    model = service.model
    scans = [load_scan(path, units=units, drop_nonfinite=True) for path in paths]
    for path, scan in zip(paths, scans, strict=True):
        dropped = scan.n_input_points - scan.n_points
        if dropped:
            echo(
                f"{path.name}: dropped {dropped:,} of {scan.n_input_points:,} points that were NaN or "
                f"infinite (missing depth pixels); fitting the other {scan.n_points:,}"
            )
    if processes is None:
        raw = sum(service.route(scan) == RAW_SCAN for scan in scans)
        processes = 2 if raw >= HELPER_SCANS else 1
    service.scan_processes = processes  # read when the first fit builds the fitters
    fits = []
    for path, scan in zip(paths, scans, strict=True):
        note(f"{path.name}: fitting as a {service.route(scan)}")  # its first progress line gives the points
        fits.append(service.fit_mesh(scan, Job(on_progress=show), hints, body))
    out.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, np.ndarray] = {
        key: np.stack([f.arrays()[key] for f in fits]) for key in fits[0].arrays()
    }
    arrays["dof_names"], arrays["joint_names"] = np.array(model.dof_names), np.array(model.joint_names)
    np.savez_compressed(out / "fit.npz", allow_pickle=False, **arrays)
    pairs = list(zip(paths, fits, strict=True))
    records = [
        {
            "mesh": str(p),
            "fitted_as": f.fitted_as,
            "dropped_points": s.n_input_points - s.n_points,
            **f.report.to_dict(),
        }
        for (p, f), s in zip(pairs, scans, strict=True)
    ]
    (out / "fit.json").write_text(json.dumps(records, indent=1) + "\n")
    for k, f in enumerate(fits):
        trimesh.Trimesh(f.vertices, model.faces, process=False).export(out / f"registration_{k:03d}.ply")
    write_mot(out / "fit.mot", model.skeleton.spec, arrays["coordinates"], arrays["root"], fps=1.0)
    for p, f in pairs:
        r = f.report
        flag = "ok" if r.confident else "LOW CONFIDENCE: " + "; ".join(r.reasons)
        # a raw scan's distances are its inliers'; the farthest of all its points shows a gross error
        peak = "" if r.scan_to_model is None else f", farthest point {r.scan_to_model.max:.0f} mm"
        echo(
            f"{p.name} ({f.fitted_as}): mean {r.distances.mean:.2f} mm, p95 {r.distances.p95:.2f} mm{peak}, "
            f"{flag}"
        )
    return records

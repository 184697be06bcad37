"""``bodyfit batch-upgrade`` and ``bodyfit batch-fit``: a whole dataset tree of sequences or scans through
:func:`bodyfit.clients.batch.batch_upgrade` / :func:`bodyfit.clients.batch_fit.batch_fit`, on a server (the
SDK), in this process or on Ray (:mod:`bodyfit.cli.backends`)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from bodyfit.cli.common import FacingHint, HeightHint, PoseHint, SexHint, UnitsOption, UpHint, fail, reported

if TYPE_CHECKING:
    from bodyfit.clients.batch import BatchReport

BACKEND_HELP = "local, a server URL (http://host:8000), ray, or ray://host:10001."


def batch_upgrade(
    dataset: Annotated[
        Path,
        typer.Argument(
            exists=True, file_okay=False, help="Folder of AMASS-style .npz sequences (searched recursively)."
        ),
    ],
    out: Annotated[Path, typer.Argument(help="Output folder (the dataset's layout is kept).")],
    concurrency: Annotated[int, typer.Option(min=1, help="Sequences in flight at once.")] = 1,
    backend: Annotated[str, typer.Option(help=BACKEND_HELP)] = "local",
    smpl_model: Annotated[
        Path | None,
        typer.Option(help="SMPL-family model file for local / ray (default $BODYFIT_SMPL_MODEL)."),
    ] = None,
    subject: Annotated[
        Path | None,
        typer.Option(
            exists=True,
            dir_okay=False,
            help="A subject file (subject.npz of `bodyfit rig`) of the one person every sequence shows: "
            "their body and bone scales in every upgrade.",
        ),
    ] = None,
) -> None:
    """Upgrade a whole dataset tree; resumes (finished sequences are skipped) and reports failures at the end
    without stopping. Writes <out>/<relative path>.npz, .json, .osim and .mot per sequence (units as
    `bodyfit upgrade` writes them)."""
    from bodyfit.cli.backends import upgrader
    from bodyfit.clients.batch import batch_upgrade as run
    from bodyfit.clients.errors import BodyfitClientError

    person = None if subject is None else subject.read_bytes()
    with reported():
        worker = upgrader(backend, concurrency, smpl_model, person)
    try:
        report = run(dataset, out, concurrency, worker)
    except (BodyfitClientError, OSError, ValueError) as exc:
        fail(exc)
    finish(report)


def batch_fit(
    scans: Annotated[
        Path,
        typer.Argument(
            exists=True, file_okay=False, help="Folder of scans (ply, obj, stl, pcd, npz; recursive)."
        ),
    ],
    out: Annotated[Path, typer.Argument(help="Output folder (the folder's layout is kept).")],
    concurrency: Annotated[int, typer.Option(min=1, help="Scans in flight at once.")] = 1,
    backend: Annotated[str, typer.Option(help=BACKEND_HELP)] = "local",
    units: UnitsOption = "auto",
    up: UpHint = None,
    facing: FacingHint = None,
    pose: PoseHint = None,
    sex: SexHint = None,
    height_m: HeightHint = None,
) -> None:
    """Fit every scan in a folder tree; resumes (finished scans are skipped) and reports failures at the end
    without stopping; the units and hints apply to every scan. Writes <out>/<relative path>.npz
    (parameters, registration, joints, to_model), .ply (the registration in the scan's frame) and .json
    (the fit report) per scan."""
    from bodyfit.cli.backends import fitter
    from bodyfit.clients.batch_fit import batch_fit as run
    from bodyfit.clients.errors import BodyfitClientError

    with reported():
        from bodyfit.service.hints import ScanHints

        hints = ScanHints.given(up, facing, pose, sex, height_m)
        worker = fitter(backend, concurrency, units, hints)
    try:
        report = run(scans, out, concurrency, worker)
    except (BodyfitClientError, OSError, ValueError) as exc:
        fail(exc)
    finish(report)


def finish(report: BatchReport) -> None:
    """List the failures on standard error, print the summary, and exit with status 1 if any failed."""
    for path, why in sorted(report.failed.items()):
        typer.echo(f"FAILED {path}: {why}", err=True)
    typer.echo(report.summary())
    if report.failed:
        raise typer.Exit(1)

"""``bodyfit batch-upgrade``: a whole dataset tree through :func:`bodyfit.clients.batch.batch_upgrade`, on a
server (the SDK), in this process or on Ray (:mod:`bodyfit.cli.backends`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from bodyfit.cli.common import fail


def batch_upgrade(
    dataset: Annotated[
        Path,
        typer.Argument(
            exists=True, file_okay=False, help="Folder of AMASS-style .npz sequences (searched recursively)."
        ),
    ],
    out: Annotated[Path, typer.Argument(help="Output folder (the dataset's layout is kept).")],
    concurrency: Annotated[int, typer.Option(min=1, help="Sequences in flight at once.")] = 1,
    backend: Annotated[
        str, typer.Option(help="local, a server URL (http://host:8000), ray, or ray://host:10001.")
    ] = "local",
    smpl_model: Annotated[
        Path | None,
        typer.Option(help="SMPL-family model file for local / ray (default $BODYFIT_SMPL_MODEL)."),
    ] = None,
) -> None:
    """Upgrade a whole dataset tree; resumes (finished sequences are skipped) and reports failures at the end
    without stopping. Writes <out>/<relative path>.npz, .json, .osim and .mot per sequence (units as
    `bodyfit upgrade` writes them)."""
    from bodyfit.cli.backends import upgrader
    from bodyfit.clients.batch import batch_upgrade as run
    from bodyfit.clients.errors import BodyfitClientError

    try:
        report = run(dataset, out, concurrency, upgrader(backend, concurrency, smpl_model))
    except (BodyfitClientError, OSError, ValueError) as exc:
        fail(exc)
    for path, why in sorted(report.failed.items()):
        typer.echo(f"FAILED {path}: {why}", err=True)
    typer.echo(report.summary())
    if report.failed:
        raise typer.Exit(1)

"""What every command shares: the error exit (status 2, one ``error:`` line, no traceback) and the help
texts of options that several commands take."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Annotated, Literal, NoReturn

import typer

from bodyfit.wire.hints import FACING_HELP, HEIGHT_HELP, POSE_HELP, SEX_HELP, UP_HELP, PoseClass, Sex

ASSETS_HELP = "Asset folder (default: assets/ of the checkout, or $BODYFIT_ASSETS)."
OUT_HELP = "Output folder (created when missing)."
SMPL_MODEL_HELP = (
    "SMPL-family model file (.npz, or .pkl without chumpy; default $BODYFIT_SMPL_MODEL; none ships)."
)


SUBJECT_HELP = (
    "A subject file (the subject.npz of `bodyfit rig`): the body is that person's, their shape and template "
    "held fixed; only the pose is fitted."
)


UNITS_HELP = (
    "Unit of the input coordinates: m (metres), mm (millimetres) or auto (whichever gives a human-sized "
    "body)."
)
SCAN_UP_HELP = f"Hint: {UP_HELP}, e.g. +z."
SCAN_FACING_HELP = f"Hint: {FACING_HELP}, e.g. +x."
SCAN_POSE_HELP = f"Hint: {POSE_HELP}."
SCAN_SEX_HELP = f"Hint: {SEX_HELP}."
SCAN_HEIGHT_HELP = f"Hint: {HEIGHT_HELP}."

Units = Literal["auto", "m", "mm"]
# The options of every command that fits raw scans (`fit scan`, `batch-fit`, `rig`): one declaration, so
# their names, checks and help texts cannot drift apart.
UnitsOption = Annotated[Units, typer.Option(help=UNITS_HELP)]
UpHint = Annotated[str | None, typer.Option(help=SCAN_UP_HELP)]
FacingHint = Annotated[str | None, typer.Option(help=SCAN_FACING_HELP)]
PoseHint = Annotated[PoseClass | None, typer.Option(help=SCAN_POSE_HELP)]
SexHint = Annotated[Sex | None, typer.Option(help=SCAN_SEX_HELP)]
HeightHint = Annotated[float | None, typer.Option(help=SCAN_HEIGHT_HELP)]


def fail(exc: BaseException | str) -> NoReturn:
    """Print ``error: <what>`` on standard error and exit with status 2 (a bad input or option)."""
    typer.echo(f"error: {exc}", err=True)
    if isinstance(exc, BaseException):
        raise typer.Exit(2) from exc
    raise typer.Exit(2)


def note(line: str) -> None:
    """Progress and notices go to standard error, so standard output holds the results alone."""
    typer.echo(line, err=True)


@contextmanager
def reported() -> Iterator[None]:
    """Turn the errors of local work (a bad file, option or asset folder: :class:`ValueError`, which every
    :class:`~bodyfit.models.errors.BodyfitError` is; :class:`OSError`; a service error) into :func:`fail`."""
    from bodyfit.service.errors import ServiceError

    try:
        yield
    except (ValueError, OSError, ServiceError) as exc:
        fail(exc)

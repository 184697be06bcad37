"""What every command shares: the error exit (status 2, one ``error:`` line, no traceback) and the help
texts of options that several commands take."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import NoReturn

import typer

ASSETS_HELP = "Asset folder (default: assets/ of the checkout, or $BODYFIT_ASSETS)."
OUT_HELP = "Output folder (created when missing)."
SMPL_MODEL_HELP = (
    "SMPL-family model file (.npz, or .pkl without chumpy; default $BODYFIT_SMPL_MODEL; none ships)."
)


SUBJECT_HELP = (
    "A subject file (the subject.npz of `bodyfit rig`): the body is that person's, their shape and template "
    "held fixed; only the pose is fitted."
)


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

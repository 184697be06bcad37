"""Deprecated: moved to :mod:`bodyfit.cli.app`; this path will be removed in the next release. Its public
names are re-exported from there, and ``python -m bodyfit.clients.cli`` still runs the command line (use
``python -m bodyfit.cli``)."""

from bodyfit.cli.app import app, main

__all__ = ["app", "main"]

if __name__ == "__main__":  # pragma: no cover
    main()

"""Deprecated: moved to :mod:`bodyfit.cli.fit.sequence`; this path will be removed in the next release. Its
public names are re-exported from there."""

from bodyfit.cli.fit.sequence import SEQUENCE_KEY, fit_sequence_files, is_sequence_file

__all__ = ["SEQUENCE_KEY", "fit_sequence_files", "is_sequence_file"]

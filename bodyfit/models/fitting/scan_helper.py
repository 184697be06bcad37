"""Deprecated: moved to :mod:`bodyfit.models.fitting.scan.helper`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.models.fitting.scan.helper import (
    ANSWER_SECONDS,
    MAX_RESTARTS,
    RESTART_SECONDS,
    STOP_SECONDS,
    ScanHelper,
)

__all__ = [
    "ANSWER_SECONDS",
    "MAX_RESTARTS",
    "RESTART_SECONDS",
    "STOP_SECONDS",
    "ScanHelper",
]

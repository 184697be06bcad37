"""What the clients send for a scan fit: a file, the bytes of one, or points (shared by REST and gRPC)."""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Protocol

import numpy as np

ScanInput = str | os.PathLike[str] | bytes | np.ndarray
SCAN_FORMATS = ("ply", "obj", "stl", "pcd", "npz")
"""The scan file formats a server reads (as :data:`bodyfit.io.scans.FORMATS`)."""


def scan_upload(scan: ScanInput, format: str | None) -> tuple[str, bytes]:
    """(file name, bytes) of a scan given as a path, as bytes with its ``format`` (ply, obj, stl, pcd or
    npz), or as an (N, 3) array of points (sent as an .npz with ``points``; metres or millimetres, as the
    fit's ``units`` say).

    Raises:
        ValueError: bytes without a format, or an array that is not (N, 3) or is sent with another format;
        TypeError: anything else.
    """
    if isinstance(scan, np.ndarray):
        if scan.ndim != 2 or scan.shape[1] != 3:
            raise ValueError(f"scan points must be an (N, 3) array; got shape {scan.shape}")
        if format not in (None, "npz"):
            raise ValueError(f"an array of points is sent as npz; leave format out (got {format!r})")
        buffer = io.BytesIO()
        np.savez(buffer, points=np.asarray(scan, np.float64))
        return "scan.npz", buffer.getvalue()
    if isinstance(scan, bytes | bytearray):
        if format is None:
            raise ValueError("give format= (ply, obj, stl, pcd or npz) when sending bytes")
        return f"scan.{format}", bytes(scan)
    if not isinstance(scan, str | os.PathLike):
        raise TypeError(
            f"scan must be a file path, bytes with format=, or an (N, 3) array of points; got "
            f"{type(scan).__name__}"
        )
    path = Path(scan)
    return (f"{path.stem}.{format}" if format else path.name), path.read_bytes()


class SubjectFile(Protocol):
    """A subject held in memory: ``bodyfit.models.rig.subject.Subject`` (``to_bytes``)."""

    def to_bytes(self) -> bytes: ...


SubjectInput = str | os.PathLike[str] | bytes | SubjectFile
"""A subject file (``bodyfit rig``, ``build_subject``): its path, its bytes, a ``Subject``, or the
``SubjectOutput`` that ``build_subject`` returned."""


def subject_upload(subject: SubjectInput | None) -> bytes | None:
    """The subject file's bytes (None stays None); the server checks them.

    Raises:
        ValueError: empty bytes or an empty file; TypeError: anything else.
    """
    if subject is None:
        return None
    if isinstance(subject, bytes | bytearray):
        data = bytes(subject)
    elif isinstance(subject, str | os.PathLike):
        data = Path(subject).read_bytes()
    elif isinstance(getattr(subject, "subject", None), bytes):  # the SDK's SubjectOutput
        data = subject.subject  # type: ignore[attr-defined]
    elif callable(getattr(subject, "to_bytes", None)):
        data = subject.to_bytes()
    else:
        raise TypeError(
            f"subject must be a subject file's path or bytes, a Subject or build_subject's result; got "
            f"{type(subject).__name__}"
        )
    if not data:
        raise ValueError("the subject file is empty; pass the .npz that `bodyfit rig` or build_subject wrote")
    return data

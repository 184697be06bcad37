"""Uploads in: the service's readers of scans, registered sequences and SMPL-format sequences, each checked
against the request limits from the file's headers before anything is decompressed or allocated (sizes
and counts: LimitExceededError, 413; anything malformed: InvalidInputError, 422). Pure functions of the
bytes and :class:`Limits`; :class:`bodyfit.service.core.BodyService` calls them with its own limits."""

from __future__ import annotations

import numpy as np

from bodyfit.io.errors import FileFormatError, FileLimitError
from bodyfit.io.npz import FLOAT, ArraySpec, Dim, read_npz
from bodyfit.io.scans import FORMATS as SCAN_FORMATS
from bodyfit.io.scans import Scan, load_scan
from bodyfit.io.smpl import SmplSequence, read_smpl_npz
from bodyfit.models.errors import BodyfitError
from bodyfit.service.errors import InvalidInputError, LimitExceededError
from bodyfit.service.limits import Limits

# Working memory per frame, measured (peak resident growth over 50-250 frames, BENCHMARKS.md): a registered
# sequence fit holds every frame's fitted mesh and report, an upgrade its proxy poses and coordinates.
SEQUENCE_BYTES_PER_FRAME = int(1.25 * 2**20)
UPGRADE_BYTES_PER_FRAME = int(0.25 * 2**20)


def read_scan(data: bytes, format: str, units: str, limits: Limits) -> Scan:
    """Read an uploaded mesh or point cloud (see :func:`bodyfit.io.scans.load_scan`).

    Raises:
        LimitExceededError: larger than ``limits.max_upload_bytes`` or ``limits.max_points``.
        InvalidInputError: unknown format, unreadable, empty, NaN, degenerate, not human-sized.
    """
    fmt = format.lower().lstrip(".")
    if fmt not in SCAN_FORMATS:
        raise InvalidInputError(
            f"unknown scan format {format!r}; send one of {', '.join(SCAN_FORMATS)} (by file name suffix "
            "or the format field)",
            field="format",
        )
    check_upload(limits, len(data))
    try:  # counts and sizes are checked from the file's header before anything is allocated
        scan = load_scan(
            data,
            format=fmt,
            units=units,
            drop_nonfinite=True,
            max_points=limits.max_points,
            max_bytes=limits.max_decompressed_bytes,
        )
    except FileLimitError as exc:
        raise LimitExceededError(str(exc), field="file") from exc
    except BodyfitError as exc:
        raise InvalidInputError(str(exc), field="file") from exc
    if scan.n_points > limits.max_points:
        raise LimitExceededError(
            f"the scan has {scan.n_points:,} points; the limit is {limits.max_points:,}: thin it "
            "(e.g. a 5 mm voxel grid keeps every detail the fit uses)",
            field="file",
        )
    return scan


def read_sequence(data: bytes, limits: Limits, n_vertices: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Read an uploaded .npz holding ``frames`` (T, V, 3) float metres in our topology and optionally
    ``weights`` (T, V) numbers, both checked from their .npy headers (dtype, shape, T against
    ``limits.max_frames``, bytes against ``limits.max_decompressed_bytes``) before they are decompressed.

    Raises:
        LimitExceededError: too large; InvalidInputError: not an npz, missing or malformed arrays.
    """
    check_upload(limits, len(data))
    V = n_vertices
    limit, fix = frame_limit(limits, SEQUENCE_BYTES_PER_FRAME)
    T = Dim("T", limit, "frames", fix)
    specs = {
        "frames": ArraySpec(
            ((T, V, 3),),
            FLOAT,
            hint="meshes in our topology, metres, saved with numpy.savez(path, frames=array); fit other "
            "topologies frame by frame as scans",
        ),
        "weights": ArraySpec(((T, V),), "fiub", required=False, hint="per-vertex weights, 0 = missing"),
    }
    try:
        arrays = read_npz(data, specs, max_bytes=limits.max_decompressed_bytes, name="the upload")
    except FileLimitError as exc:
        raise LimitExceededError(str(exc), field=exc.key or "file") from exc
    except FileFormatError as exc:
        raise InvalidInputError(str(exc), field=exc.key or "file") from exc
    frames = arrays["frames"]
    if len(frames) == 0:
        raise InvalidInputError(f"frames holds no frames; send (T, {V}, 3) with T >= 1", field="frames")
    return frames, arrays.get("weights")


def read_upgrade(data: bytes, filename: str, limits: Limits) -> SmplSequence:
    """Read an uploaded AMASS-style .npz (SMPL .pkl files are refused: uploads are never unpickled).

    Raises:
        LimitExceededError: too large or too many frames; InvalidInputError: unreadable or malformed.
    """
    check_upload(limits, len(data))
    if filename.lower().endswith(".pkl"):
        raise InvalidInputError(
            "the server does not unpickle uploads (a pickle can run code); convert the .pkl to an "
            "AMASS-style .npz (numpy.savez with poses, trans, betas, gender, mocap_framerate)",
            field="file",
        )
    limit, fix = frame_limit(limits, UPGRADE_BYTES_PER_FRAME)
    try:  # poses, trans, betas, ... checked from their headers; frames and bytes against the limits
        sequence = read_smpl_npz(
            data, filename or "upload.npz", max_frames=limit, max_bytes=limits.max_decompressed_bytes
        )
    except FileLimitError as exc:
        raise LimitExceededError(
            str(exc) if limit == limits.max_frames else f"{exc} ({fix})", field="file"
        ) from exc
    except BodyfitError as exc:
        raise InvalidInputError(str(exc), field="file") from exc
    if sequence.n_frames > limit:
        raise LimitExceededError(
            f"{sequence.n_frames:,} frames sent; the limit is {limit:,}: {fix}", field="file"
        )
    return sequence


def frame_limit(limits: Limits, bytes_per_frame: int) -> tuple[int, str]:
    """The most frames one request may hold: ``limits.max_frames``, or fewer where their estimated
    working memory (``bytes_per_frame`` each) would pass ``limits.max_request_bytes``; and how to
    split the work, for the refusal's message."""
    budget = limits.max_request_bytes // bytes_per_frame
    if budget >= limits.max_frames:
        return limits.max_frames, "split the sequence into overlapping parts"
    return max(1, budget), (
        f"the server's memory budget for one request (BODYFIT_MAX_REQUEST_MB = "
        f"{limits.max_request_bytes / 2**20:.0f}) holds {budget:,} frames of this work: split the "
        "sequence into overlapping parts of at most that many frames"
    )


def check_upload(limits: Limits, n_bytes: int) -> None:
    """The upload's size against ``limits.max_upload_bytes`` (its decompressed arrays are checked
    against ``limits.max_decompressed_bytes`` by the readers, from their headers)."""
    if n_bytes > limits.max_upload_bytes:
        raise LimitExceededError(
            f"the upload is {n_bytes / 2**20:.1f} MiB; the limit is "
            f"{limits.max_upload_bytes / 2**20:.0f} MiB: thin or split it",
            field="file",
        )
